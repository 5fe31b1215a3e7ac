"""Third-order extended state observer (ESO) for one channel y'' = f + b*u, in discrete time.

Why discrete: the authors integrated their continuous ESO with explicit Euler at the loop period
(munzir/18h-krang-utils eso.hpp). With their gains L = (1160, 173438.396, 1343839.408)
the continuous poles are -985.4, -166.4 and -8.19 rad/s, and Euler is stable only for
h < 2/985.4 = 2.03 ms; the hardware loop runs at ~30 Hz (h = 33 ms). `euler_transition_matrix`
reproduces that scheme so the instability can be shown (spectral radius 1.96 at 3 ms).

This module offers two discretisations that are stable at every sample period h > 0:

* ``'current'`` (default): the discrete "current" ESO of Miklosovic, Radke & Gao (ACC 2006).
  Predict with the exact ZOH model of the chain of integrators, then
  correct with the measurement of the same instant::

      z- = Ad z[k-1] + Bd u[k-1];   z[k] = z- + L (y[k] - z-[0])

  Its error dynamics are e[k] = (I - L C) Ad e[k-1]. The gain L is either the bandwidth design
  (all three eigenvalues at beta = exp(-w_o h), closed form below) or the authors' continuous
  gains with the poles *matched*: eigenvalues at exp(p_i h), p_i the roots of
  s^3 + l1 s^2 + l2 s + l3 (Ackermann on the pair (Ad, C Ad)).
* ``'zoh'``: the authors' continuous observer dz/dt = (A - L C) z + B u + L y sampled exactly
  with a zero-order hold on u and y. Eigenvalues exp(p_i h) as well, but it is a predictor:
  the estimate at k uses y[k-1] (one sample of lag), and holding y between samples biases f_hat
  whenever y moves (the authors' l3 = 1.3e6 amplifies that hold error; closed loops built on it
  went unstable at 10 ms in our double-integrator trials). Kept for analysis; use 'current'.

State z = [y_hat, ydot_hat, f_hat]. The observer is initialised from the measurement (y_hat = y,
optional measured rate, f_hat = 0) to avoid peaking. ``f_limit`` optionally saturates f_hat
(both the output and the internal state, so the estimate cannot wind up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm

#: The authors' continuous ESO gains (both channels), munzir/18d Controller.cpp.
AUTHORS_CONTINUOUS_GAINS = (1160.0, 173438.396, 1343839.408)

_C = np.array([[1.0, 0.0, 0.0]])
_A_CONT = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])


def chain_model(h: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH discretisation (Ad, Bd) of z' = [z2, z3 + b u, 0] over one period h."""
    ad = np.array([[1.0, h, 0.5 * h * h], [0.0, 1.0, h], [0.0, 0.0, 1.0]])
    bd = np.array([0.5 * b * h * h, b * h, 0.0])
    return ad, bd


def continuous_bandwidth_gains(omega_o: float) -> np.ndarray:
    """Gao's bandwidth parameterisation: L = (3w, 3w^2, w^3), a triple pole at -w (continuous)."""
    w = float(omega_o)
    return np.array([3.0 * w, 3.0 * w * w, w**3])


def bandwidth_gains(omega_o: float, h: float) -> np.ndarray:
    """Current-ESO gains with all eigenvalues of (I - L C) Ad at beta = exp(-omega_o h) (notes
    §5)."""
    if omega_o <= 0 or h <= 0:
        raise ValueError('omega_o and h must be positive')
    beta = np.exp(-omega_o * h)
    return np.array(
        [1.0 - beta**3, 1.5 / h * (1.0 - beta) ** 2 * (1.0 + beta), (1.0 - beta) ** 3 / h**2]
    )


def continuous_poles(l_cont) -> np.ndarray:
    """Poles of the continuous observer, roots of s^3 + l1 s^2 + l2 s + l3."""
    l1, l2, l3 = (float(v) for v in l_cont)
    return np.roots([1.0, l1, l2, l3])


def current_gains_for_poles(z_poles, h: float) -> np.ndarray:
    """Current-ESO gain L placing eig((I - L C) Ad) at z_poles (Ackermann on (Ad, C Ad)).

    Written out rather than calling ct.place, which rejects repeated poles (notes §5).
    """
    ad, _ = chain_model(h, 1.0)
    c_tilde = _C @ ad  # error dynamics Ad - L (C Ad)
    obs = np.vstack([c_tilde, c_tilde @ ad, c_tilde @ ad @ ad])
    coeffs = np.real(np.poly(np.asarray(z_poles, dtype=complex)))  # z^3 + a1 z^2 + a2 z + a3
    phi = ad @ ad @ ad + coeffs[1] * ad @ ad + coeffs[2] * ad + coeffs[3] * np.eye(3)
    return (phi @ np.linalg.solve(obs, np.array([0.0, 0.0, 1.0]))).ravel()


def matched_gains(l_cont, h: float) -> np.ndarray:
    """Current-ESO gains whose eigenvalues are exp(p_i h) for the continuous gains' poles p_i."""
    return current_gains_for_poles(np.exp(continuous_poles(l_cont) * h), h)


def euler_transition_matrix(l_cont, h: float) -> np.ndarray:
    """Error-transition matrix I + h (A - L C) of the authors' explicit-Euler ESO (for
    comparison)."""
    lc = np.asarray(l_cont, dtype=float).reshape(3, 1)
    return np.eye(3) + h * (_A_CONT - lc @ _C)


def spectral_radius(m: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(m))))


@dataclass(frozen=True)
class EsoConfig:
    """The ADRC's observers (parameters ``adrc.eso.*``). The controller ships a bandwidth design:
    the authors' gains (poles -985, -166, -8.19 rad/s) were tuned in a noiseless 1 kHz sim; with
    0.1 deg of IMU noise at 500 Hz they raise the wheel-current noise at rest from 0.4 A (plain
    LQR) to 4.2 A std and the theta ESO's f_hat noise from 0.065 to 1.9 rad/s^2 (docs/control.md).
    """

    method: str = field(
        default='current',
        metadata={
            'doc': "discretisation: 'current' (stable at every period) or 'zoh' (analysis only)"
        },
    )
    omega_o: float = field(
        default=20.0,
        metadata={
            'doc': 'bandwidth (triple pole), rad/s, ~5x the fastest LQR(q) closed-loop pole; '
            "0 = the authors' continuous gains (continuous_gains)"
        },
    )
    continuous_gains: tuple[float, ...] = field(
        default=AUTHORS_CONTINUOUS_GAINS,
        metadata={
            'doc': "(l1, l2, l3) of a continuous design, used when omega_o is 0 (the authors')"
        },
    )

    def __post_init__(self):
        if self.method not in ('current', 'zoh'):
            raise ValueError("eso.method must be 'current' or 'zoh'")
        if self.omega_o < 0 or len(self.continuous_gains) != 3:
            raise ValueError('eso.omega_o must not be negative; continuous_gains needs 3 values')


@dataclass
class _Discretisation:
    h: float
    phi: np.ndarray  # error-transition matrix
    gain: np.ndarray  # L (current form) or None-equivalent
    gam_u: np.ndarray  # input matrix for u[k-1]
    gam_y: np.ndarray  # measurement matrix (y[k] for current, y[k-1] for zoh)


class ExtendedStateObserver:
    """Discrete third-order ESO for y'' = f + b u; see the module docstring for the schemes.

    Parameters
    ----------
    b : input gain of the channel (e.g. b_x or b_theta from the linearised WIP).
    h : nominal sample period [s]. ``update(..., dt=...)`` re-discretises for other periods
        (cached by dt rounded to 1e-6 s), so jittery loop timing stays consistent.
    omega_o : observer bandwidth [rad/s] for the bandwidth design (``'current'`` method only).
    continuous_gains : (l1, l2, l3) of a continuous design; default the authors' gains
        (munzir/18d) when ``omega_o`` is not given.
    method : ``'current'`` (matched poles / bandwidth, uses y[k]) or ``'zoh'`` (exact sampling of
        the continuous observer, uses y[k-1]).
    f_limit : optional bound on |f_hat| (same unit as y'').
    """

    def __init__(
        self,
        b: float,
        h: float,
        *,
        omega_o: float | None = None,
        continuous_gains=None,
        method: str = 'current',
        f_limit: float | None = None,
    ):
        if h <= 0:
            raise ValueError('sample period h must be positive')
        if method not in ('current', 'zoh'):
            raise ValueError("method must be 'current' or 'zoh'")
        if omega_o is not None and continuous_gains is not None:
            raise ValueError('give either omega_o or continuous_gains, not both')
        if omega_o is not None and method == 'zoh':
            continuous_gains = continuous_bandwidth_gains(omega_o)
            omega_o = None
        if omega_o is None and continuous_gains is None:
            continuous_gains = AUTHORS_CONTINUOUS_GAINS
        self.b = float(b)
        self.h = float(h)
        self.omega_o = None if omega_o is None else float(omega_o)
        self.continuous_gains = (
            None if continuous_gains is None else np.asarray(continuous_gains, float)
        )
        self.method = method
        self.f_limit = None if f_limit is None else abs(float(f_limit))
        self._cache: dict[float, _Discretisation] = {}
        self._floats: dict[float, tuple] = {}
        self._last_dt = self._last = None
        self.z = [0.0, 0.0, 0.0]  # floats: numpy's per-call cost on 3-vectors dominates a
        self._y_prev = 0.0  # 500 Hz loop
        self._initialised = False

    @classmethod
    def from_config(
        cls, b: float, h: float, config: EsoConfig, f_limit: float | None = None
    ) -> 'ExtendedStateObserver':
        if config.omega_o:
            return cls(b, h, omega_o=config.omega_o, method=config.method, f_limit=f_limit)
        return cls(
            b, h, continuous_gains=config.continuous_gains, method=config.method, f_limit=f_limit
        )

    # ------------------------------------------------------------------ design
    def discretisation(self, h: float | None = None) -> _Discretisation:
        h = self.h if h is None else float(h)
        key = round(h, 6)
        d = self._cache.get(key)
        if d is None:
            d = self._discretise(h)
            if len(self._cache) > 64:
                self._cache.clear()
            self._cache[key] = d
        return d

    def _discretise(self, h: float) -> _Discretisation:
        ad, bd = chain_model(h, self.b)
        if self.method == 'current':
            if self.omega_o is not None:
                gain = bandwidth_gains(self.omega_o, h)
            else:
                gain = matched_gains(self.continuous_gains, h)
            ilc = np.eye(3) - np.outer(gain, _C)
            return _Discretisation(h, ilc @ ad, gain, ilc @ bd, gain)
        # exact ZOH of dz = (A - L C) z + B u + L y with inputs (u, y) held over the period
        lc = self.continuous_gains.reshape(3, 1)
        aug = np.zeros((5, 5))
        aug[:3, :3] = _A_CONT - lc @ _C
        aug[:3, 3] = [0.0, self.b, 0.0]
        aug[:3, 4] = lc.ravel()
        e = expm(aug * h)
        return _Discretisation(h, e[:3, :3], lc.ravel(), e[:3, 3], e[:3, 4])

    def set_b(self, b: float) -> None:
        """New input gain (e.g. after an LQR(q) update); the estimate itself is kept."""
        if float(b) != self.b:
            self.b = float(b)
            self._cache.clear()
            self._floats.clear()
            self._last_dt = self._last = None

    @property
    def gain(self) -> np.ndarray:
        return self.discretisation().gain

    def transition_matrix(self, h: float | None = None) -> np.ndarray:
        """Error-transition matrix at period h; all eigenvalues inside the unit circle."""
        return self.discretisation(h).phi

    # ------------------------------------------------------------------ running
    def reset(self, y0: float, ydot0: float = 0.0, f0: float = 0.0) -> None:
        """Start from the measurement (no initial-error peaking)."""
        self.z = [float(y0), float(ydot0), float(f0)]
        self._y_prev = float(y0)
        self._initialised = True

    def shift(self, dy: float, df: float = 0.0) -> None:
        """Move the estimate by dy (and f_hat by df) without a transient: the measurement's origin
        moved (e.g. a new CoM model changed theta) while the plant did not."""
        z = self.z
        z[0] += dy
        z[2] += df
        self._y_prev += dy

    def _float_discretisation(self, dt):
        key = round(self.h if dt is None else dt, 6)
        d = self._floats.get(key)
        if d is None:
            if dt is not None and key != round(self.h, 6) and self._closed_form:
                # samples timed by arrival: nearly every dt is new, and the numpy design costs
                # ~0.1 ms per observer and step (a fifth of a 500 Hz period for the two)
                d = self._bandwidth_floats(float(dt))
            else:
                m = self.discretisation(dt)
                d = (
                    tuple(float(v) for v in m.phi.ravel()),
                    tuple(float(v) for v in m.gam_u),
                    tuple(float(v) for v in m.gam_y),
                )
            if len(self._floats) > 64:
                self._floats.clear()
            self._floats[key] = d
        return d

    @property
    def _closed_form(self) -> bool:
        return self.method == 'current' and self.omega_o is not None

    def _bandwidth_floats(self, h: float) -> tuple:
        """`_discretise(h)` of the current ESO with bandwidth gains, written out in floats:
        phi = (I - L C) Ad, gam_u = (I - L C) Bd, gam_y = L (chain_model, bandwidth_gains)."""
        beta = math.exp(-self.omega_o * h)
        g0 = 1.0 - beta**3
        g1 = 1.5 / h * (1.0 - beta) ** 2 * (1.0 + beta)
        g2 = (1.0 - beta) ** 3 / h**2
        hh = 0.5 * h * h
        bu0, bu1 = self.b * hh, self.b * h
        phi = (
            (1.0 - g0),
            (1.0 - g0) * h,
            (1.0 - g0) * hh,
            -g1,
            1.0 - g1 * h,
            h - g1 * hh,
            -g2,
            -g2 * h,
            1.0 - g2 * hh,
        )
        return phi, ((1.0 - g0) * bu0, bu1 - g1 * bu0, -g2 * bu0), (g0, g1, g2)

    def update(self, y: float, u_prev: float, dt: float | None = None) -> list:
        """One step: y = measurement now, u_prev = input applied over the last period. Returns
        [y_hat, ydot_hat, f_hat]."""
        self.step(y, u_prev, dt)
        return list(self.z)

    def step(self, y: float, u_prev: float, dt: float | None = None) -> None:
        """``update`` without the copy of the state (the control loop reads ``z``)."""
        if not self._initialised:
            self.reset(y)
            return
        if dt != self._last_dt or self._last is None:
            self._last = self._float_discretisation(dt)
            self._last_dt = dt
        p, gu, gy = self._last
        if self.method == 'zoh':  # a predictor: it uses the previous measurement
            y, self._y_prev = self._y_prev, y
        z = self.z
        z0, z1, z2 = z
        u = u_prev
        n2 = p[6] * z0 + p[7] * z1 + p[8] * z2 + gu[2] * u + gy[2] * y
        flim = self.f_limit
        if flim is not None:
            n2 = -flim if n2 < -flim else (flim if n2 > flim else n2)
        z[0] = p[0] * z0 + p[1] * z1 + p[2] * z2 + gu[0] * u + gy[0] * y
        z[1] = p[3] * z0 + p[4] * z1 + p[5] * z2 + gu[1] * u + gy[1] * y
        z[2] = n2

    @property
    def y_hat(self) -> float:
        return float(self.z[0])

    @property
    def ydot_hat(self) -> float:
        return float(self.z[1])

    @property
    def f_hat(self) -> float:
        return float(self.z[2])
