"""LQR(q) for the locked-joint WIP, with a pose/beta-keyed gain cache and the ADRC gain split.

State order (ours, as returned by ``krang_model.wip.linearize``): X = [x, xdot, theta, thetadot],
input = total wheel torque [N m] (both wheels together), u = -K X.

Weights. FACTS §7 quotes Q = diag(300, 96000, 30000, 90000), R = 500 next to the 18h state order
(theta, thetadot, x, xdot). That pairing is wrong: the numbers come from munzir/18d Controller.cpp,
whose state order is (thCOM, thWheel, dthCOM, dthWheel), and the later hardware repo
(munzir/18i Q.txt) writes the same weights as diag(300, 30000, 96000, 90000) in the 18h order.
Both say: theta 300, thetadot 30000, x 96000, xdot 90000 (x in wheel radians). A third check:
for a plant whose x is a free integrator, Kalman's return-difference equality at w -> 0 gives
|K_x| = sqrt(Q_x / R); sqrt(96000 / 500) = 13.8564, exactly the x gain FACTS §7 lists for the
hardware (-13.8564), whereas 30000 would give 7.75. Mapped to our order:

    Q = diag(Q_x, Q_xdot, Q_theta, Q_thetadot) = diag(96000, 90000, 300, 30000), R = 500.

If the model's x is in metres instead of wheel radians, pass ``position_unit='m'`` and the wheel
radius: the x and xdot weights are divided by r^2 so the design is the same controller.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Callable

import control as ct
import numpy as np

#: Authors' weights mapped to our state order [x, xdot, theta, thetadot] (see module docstring).
AUTHORS_Q_DIAG = (96000.0, 90000.0, 300.0, 30000.0)
#: Authors' input weight (FACTS §7).
AUTHORS_R = 500.0


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
    """Q, R in our state order; defaults are the authors' weights (FACTS §7, remapped above).

    Parameters
    ----------
    q_diag : diagonal of Q over [x, xdot, theta, thetadot], with x in wheel radians.
    r : input weight on the total wheel torque.
    position_unit : ``'rad'`` (x in wheel radians, the authors' convention) or ``'m'``.
    wheel_radius_m : needed when position_unit == 'm' (config drivetrain / URDF).
    """

    def __init__(self, q_diag=AUTHORS_Q_DIAG, r: float = AUTHORS_R, *,
                 position_unit: str = 'rad', wheel_radius_m: float | None = None):
        q = np.asarray(q_diag, float).ravel()
        if q.size != 4 or np.any(q < 0):
            raise ValueError('q_diag must be 4 non-negative numbers')
        if r <= 0:
            raise ValueError('R must be positive')
        if position_unit == 'm':
            if not wheel_radius_m or wheel_radius_m <= 0:
                raise ValueError("position_unit='m' needs wheel_radius_m")
            q = q.copy()
            q[:2] /= wheel_radius_m ** 2
        elif position_unit != 'rad':
            raise ValueError("position_unit must be 'rad' or 'm'")
        self.q = np.diag(q)
        self.r = float(r)

    def gain(self, a, b) -> np.ndarray:
        return lqr_gain(a, b, self.q, self.r)


class GainCache:
    """LQR(q) recomputed only when the rounded (pose, beta) key changes.

    ``linearize(pose, beta) -> (A, B)`` is any callable (the lead's ``krang_model.wip.linearize``
    wrapped as needed). Keys round pose to ``pose_decimals`` (rad) and beta to ``beta_decimals``;
    a small LRU keeps the last ``maxsize`` designs so oscillating between two poses is free.
    """

    def __init__(self, linearize: Callable, designer: LqrDesigner | None = None, *,
                 pose_decimals: int = 3, beta_decimals: int = 6, maxsize: int = 8):
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
