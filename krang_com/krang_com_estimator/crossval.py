"""k-fold cross-validation on balanced poses: the fold split, and the held-out predictions of any
fit (cross_validate_fit) or of a registered estimator (cross_validate)."""

import numpy as np

from krang_model.com import phi as phi_fn

from .registry import make_estimator
from .rows import pitch_rows


def fold_split(n, folds=10, seed=0):
    """The held-out index sets of a k-fold split of n records (2 <= k <= n), from `seed`."""
    folds = max(2, min(int(folds), n))
    return np.array_split(np.random.default_rng(seed).permutation(n), folds)


def cross_validate_fit(fit, robot, q_base, joints, folds=10, seed=0):
    """k-fold CV of `fit(train_indices) -> (beta, pitch_offset or None)`: the prediction
    x_com = phi^T beta on each held-out record and the pitch error atan2(x_com, psi^T beta), at
    the measured pitch less the pitch offset where the fit estimated one. Training indices are
    sorted (records keep their order)."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    joints = np.atleast_2d(joints)
    n = len(q_base)
    P = phi_fn(robot, q_base, joints)
    Psi = pitch_rows(robot, q_base, joints)
    pred = np.empty(n)
    pitch = np.empty(n)
    for f in fold_split(n, folds, seed):
        tr = np.setdiff1d(np.arange(n), f)
        beta, offset = fit(tr)
        Pf, Psif = P[f], Psi[f]
        if offset:
            Pf, Psif = (
                phi_fn(robot, q_base[f] - offset, joints[f]),
                pitch_rows(robot, q_base[f] - offset, joints[f]),
            )
        pred[f] = Pf @ beta
        pitch[f] = np.arctan2(pred[f], Psif @ beta)
    return pred, pitch


def cross_validate(method, robot, q_base, joints, beta0, folds=10, seed=0, **kw):
    """cross_validate_fit of the registered estimator `method` (options `kw`): its batch `fit` on
    the training records, and its `pitch_offset` if it estimated one."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    joints = np.atleast_2d(joints)

    def fit(tr):
        estimator = make_estimator(method, robot, beta0, **kw)
        beta, _ = estimator.fit(q_base[tr], joints[tr])
        return beta, getattr(estimator, 'pitch_offset', None)

    return cross_validate_fit(fit, robot, q_base, joints, folds, seed)
