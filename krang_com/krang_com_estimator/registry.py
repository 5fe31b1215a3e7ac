"""The estimator registry and the update protocol every estimator follows.

One registry (ESTIMATORS, filled by @register_estimator; make_estimator(name, robot, beta0,
**options)) and one protocol (Estimator: `update(q_base, joints)` learns from one balanced pose
with the estimator's own measurement model and returns the paper's x_com error before the update;
`beta`, `covariance`, `n_updates`, `reset(beta0=None)`, and the batch `fit(q_base, joints)`;
`update` also takes an optional `sigma`, the pose's pitch std in rad). The built-in estimators
(krang_com_estimator.estimators) register when the package is imported; plug-ins through the
entry-point group.
"""

import importlib.metadata
import inspect

import numpy as np


#: name -> Estimator subclass; filled by @register_estimator (built-ins, plug-ins)
ESTIMATORS = {}
ENTRY_POINT_GROUP = 'krang_com.estimators'
_plugins_loaded = False


def register_estimator(name):
    """Class decorator: make an Estimator subclass available by `name` to make_estimator, and so to
    the com_estimator node's `method` parameter, `krang learn/relearn --method`, the closed loop
    and the experiments. Register your own the same way, in a module imported before the CLI is
    built or named in the `krang_com.estimators` entry-point group of your package."""

    def add(cls):
        if ESTIMATORS.get(name, cls) is not cls:
            raise ValueError(
                f'estimator {name!r} is already registered ({ESTIMATORS[name].__name__})'
            )
        cls.name = name
        ESTIMATORS[name] = cls
        return cls

    return add


def _load_plugins():
    """Import the modules of the entry-point group once (each registers its estimators)."""
    global _plugins_loaded
    if not _plugins_loaded:
        _plugins_loaded = True
        for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
            ep.load()


def estimator_names():
    """The registered names, built-in ones first (the CLI's --method choices)."""
    _load_plugins()
    return tuple(ESTIMATORS)


def make_estimator(name, robot, beta0, **options):
    """A registered estimator: ESTIMATORS[name](robot, beta0, **options). Options its constructor
    does not take are dropped (unless it takes **kwargs), so one set of options, e.g. the CLI's,
    serves every method."""
    _load_plugins()
    if name not in ESTIMATORS:
        raise ValueError(f'unknown estimator {name!r}; choose one of {tuple(ESTIMATORS)}')
    cls = ESTIMATORS[name]
    params = inspect.signature(cls).parameters
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        options = {k: v for k, v in options.items() if k in params}
    return cls(robot, beta0, **options)


class Estimator:
    """The update protocol of every registered estimator.

    `cls(robot, beta0, **options)`; `update(q_base, joints)` learns from one balanced pose
    (measured base pitch in rad, joints in pose order) with the estimator's own measurement model
    and returns the paper's x_com error before the update; `beta`, `covariance` (None if it has
    none), `n_updates`, `errors` (x_com error before each update); `reset(beta0=None)` starts over
    (from a new beta0 if given; options derived from beta0 at construction are kept); `fit(q_base,
    joints)` learns from a batch and returns (beta, info): by default one update per pose in the
    given order, overridden where a closed form exists (map)."""

    name = 'estimator'

    def __init__(self, robot, beta0):
        self.robot = robot
        self.beta0 = np.array(beta0, dtype=float)
        self.reset()

    def reset(self, beta0=None):
        if beta0 is not None:
            self.beta0 = np.array(beta0, dtype=float)
        self._beta = self.beta0.copy()
        self.n_updates = 0
        self.errors = []

    @property
    def beta(self):
        return self._beta.copy()

    @property
    def covariance(self):
        return None

    def update(self, q_base, joints, sigma=None):
        """Learn from one balanced pose; `sigma` (optional): the pose's own pitch standard error
        in rad (the detector's), which estimators with a noise model add to it for this pose."""
        raise NotImplementedError

    def fit(self, q_base, joints):
        """Learn from the poses (rows of joints, measured q_base), from beta0: (beta, info)."""
        q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
        joints = np.atleast_2d(joints)
        self.reset()
        for qb, jt in zip(q_base, joints):
            self.update(qb, jt)
        return self.beta, {'method': self.name, 'poses': int(len(q_base)), **self.fit_info()}

    def fit_info(self):
        """Extra facts for fit()'s info dict."""
        return {}
