"""LQR(q) for the locked-joint WIP, with a pose/beta-keyed gain cache and the ADRC gain split.

State order (ours, as returned by ``krang_model.wip.linearize``): X = [x, xdot, theta, thetadot],
input = total wheel torque [N m] (both wheels together), u = -K X.

Weights. The kit's summary quotes Q = diag(300, 96000, 30000, 90000), R = 500 next to the 18h order
(theta, thetadot, x, xdot). That pairing is wrong: the numbers come from munzir/18d Controller.cpp,
whose state order is (thCOM, thWheel, dthCOM, dthWheel), and the later hardware repo
(munzir/18i Q.txt) writes the same weights as diag(300, 30000, 96000, 90000) in the 18h order.
Both say: theta 300, thetadot 30000, x 96000, xdot 90000 (x in wheel radians). A third check:
for a plant whose x is a free integrator, Kalman's return-difference equality at w -> 0 gives
|K_x| = sqrt(Q_x / R); sqrt(96000 / 500) = 13.8564, exactly the hardware's x gain (-13.8564),
whereas 30000 would give 7.75. Mapped to our order:

    Q = diag(Q_x, Q_xdot, Q_theta, Q_thetadot) = diag(96000, 90000, 300, 30000), R = 500.

If the model's x is in metres instead of wheel radians, pass ``position_unit='m'`` and the wheel
radius: the x and xdot weights are divided by r^2 so the design is the same controller.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Callable

import control as ct
import numpy as np

#: Authors' weights mapped to our state order [x, xdot, theta, thetadot] (see module docstring).
AUTHORS_Q_DIAG = (96000.0, 90000.0, 300.0, 30000.0)
#: Authors' input weight (munzir/18d Controller.cpp).
AUTHORS_R = 500.0


@dataclass(frozen=True)
class LqrConfig:
    """LQR(q) weights and when the controller redoes the design (parameters ``lqr.*``)."""

    q_diag: tuple[float, ...] = field(
        default=AUTHORS_Q_DIAG,
        metadata={
            'doc': "Q over [x, xdot, theta, thetadot] with x in WHEEL RADIANS (the authors' "
            'weights, '
            're-ordered: krang_adrc_controller/lqr.py); a controller in metres rescales them'
        },
    )
    r: float = field(default=AUTHORS_R, metadata={'doc': 'R on the total wheel torque'})
    gain_update_period_s: float = field(
        default=0.1,
        metadata={'doc': 'while the joints move: LQR(q) redesign at most this often, s'},
    )
    pose_update_period_s: float = field(
        default=0.02,
        metadata={'doc': 'while the joints move: CoM-offset (theta) update period, s'},
    )
    pose_tol_rad: float = field(
        default=2e-3,
        metadata={'doc': 'a settled pose counts as changed when a joint leaves this band, rad'},
    )
    pose_check_period_s: float = field(
        default=0.1, metadata={'doc': 'how often a settled pose is compared with its reference, s'}
    )

    def __post_init__(self):
        if len(self.q_diag) != 4 or any(q < 0 for q in self.q_diag) or self.r <= 0:
            raise ValueError('lqr.q_diag needs 4 non-negative entries and lqr.r > 0')


def lqr_gain(a, b, q, r) -> np.ndarray:
    """Continuous LQR gain K (shape (4,)) with python-control; u = -K x."""
    a = np.asarray(a, float)
    b = np.asarray(b, float).reshape(a.shape[0], -1)
    k, _, _ = ct.lqr(a, b, np.asarray(q, float), np.atleast_2d(np.asarray(r, float)))
    return np.asarray(k, float).ravel()


def split_gains(k) -> tuple[np.ndarray, np.ndarray]:
    """(F_x, F_theta) from K over [x, xdot, theta, thetadot], for u_x = -F_x.[x, xdot] etc."""
    k = np.asarray(k, float).ravel()
    if k.size != 4:
        raise ValueError('expected a 4-element gain')
    return k[:2].copy(), k[2:].copy()


def channel_input_gains(b) -> tuple[float, float]:
    """(b_x, b_theta): the xddot and thetaddot rows of B, the ESO input gains."""
    b = np.asarray(b, float).ravel()
    if b.size != 4:
        raise ValueError('expected B with 4 rows')
    return float(b[1]), float(b[3])


class LqrDesigner:
    """Q, R in our state order; defaults are the authors' weights (remapped above).

    Parameters
    ----------
    config : the weights (``LqrConfig.q_diag`` with x in wheel radians, ``LqrConfig.r``).
    position_unit : ``'rad'`` (x in wheel radians, the authors' convention) or ``'m'``.
    wheel_radius_m : needed when position_unit == 'm' (config drivetrain / URDF).
    """

    def __init__(
        self,
        config: LqrConfig = LqrConfig(),
        *,
        position_unit: str = 'rad',
        wheel_radius_m: float | None = None,
    ):
        q = np.asarray(config.q_diag, float).ravel()
        if position_unit == 'm':
            if not wheel_radius_m or wheel_radius_m <= 0:
                raise ValueError("position_unit='m' needs wheel_radius_m")
            q = q.copy()
            q[:2] /= wheel_radius_m**2
        elif position_unit != 'rad':
            raise ValueError("position_unit must be 'rad' or 'm'")
        self.q = np.diag(q)
        self.r = float(config.r)

    def gain(self, a, b) -> np.ndarray:
        return lqr_gain(a, b, self.q, self.r)


class GainCache:
    """LQR(q) recomputed only when the rounded (pose, beta) key changes.

    ``linearize(pose, beta) -> (A, B)`` is any callable (``krang_model.wip.linearize``
    wrapped as needed). Keys round pose to ``pose_decimals`` (rad) and beta to ``beta_decimals``;
    a small LRU keeps the last ``maxsize`` designs so oscillating between two poses is free.
    """

    def __init__(
        self,
        linearize: Callable,
        designer: LqrDesigner | None = None,
        *,
        pose_decimals: int = 3,
        beta_decimals: int = 6,
        maxsize: int = 8,
    ):
        self.linearize = linearize
        self.designer = designer or LqrDesigner()
        self.pose_decimals = pose_decimals
        self.beta_decimals = beta_decimals
        self.maxsize = maxsize
        self.recomputations = 0
        self._lru: OrderedDict = OrderedDict()

    def key(self, pose, beta) -> tuple:
        p = tuple(np.round(np.asarray(pose, float).ravel(), self.pose_decimals) + 0.0)
        bt = tuple(np.round(np.asarray(beta, float).ravel(), self.beta_decimals) + 0.0)
        return p, bt

    def design(self, pose, beta) -> dict:
        """{'K', 'F_x', 'F_theta', 'b_x', 'b_theta', 'A', 'B'} for this pose and beta."""
        k = self.key(pose, beta)
        hit = self._lru.get(k)
        if hit is not None:
            self._lru.move_to_end(k)
            return hit
        a, b = self.linearize(pose, beta)
        a = np.asarray(a, float)
        b = np.asarray(b, float).ravel()
        gain = self.designer.gain(a, b)
        f_x, f_th = split_gains(gain)
        b_x, b_th = channel_input_gains(b)
        out = {'K': gain, 'F_x': f_x, 'F_theta': f_th, 'b_x': b_x, 'b_theta': b_th, 'A': a, 'B': b}
        self.recomputations += 1
        self._lru[k] = out
        if len(self._lru) > self.maxsize:
            self._lru.popitem(last=False)
        return out
