"""The WIP model stepped over a large batch, compiled: many parameter sets x many windows x many
sub-steps (the discrepancy replay's predictions, billions of element sub-steps per run).

The physics is ``krang_model.wip``'s own functions (``pitch_equations``, ``body_terms``,
``adjusted_body``, ``semi_implicit_euler``), compiled by numba into one loop; this module adds
only the loop, the gathering of each element's body, torque and drive train, and the sines and
cosines of the CoM angle. Why compiled: stepped as numpy arrays, every operation of a sub-step is
a pass over memory and a sine or a tanh costs 10-50 multiplies; compiled, a block of elements
stays in the first-level cache through all its sub-steps and runs in SIMD lanes (the equations'
``smooth_sign`` compiles to ``simd_tanh``, which needs no library call).

The sines and cosines of theta = q_base + com offset are computed exactly every ``anchor``
sub-steps and carried in between by rotation through each sub-step's angle increment (a Taylor
series to the 6th order: off by less than 5e-15 for increments up to 0.03 rad); the floor slope's
tilt is theta rotated by the slope. With ``anchor=1`` every sub-step is ``WipDynamics.step_pitch``
on floats to rounding.

The loop is compiled on first use (about 1.5 s) and cached on disk (numba's cache, in the package's
``__pycache__`` or the user's cache directory), under a key that holds the hash of
``krang_model.wip``'s source: a change of the physics compiles it again.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
from numba import njit
from numba.extending import overload, register_jitable

from . import wip
from .wip import (
    adjusted_body,
    body_terms,
    caster_torque,
    pitch_equations,
    semi_implicit_euler,
    smooth_sign,
)

#: elements stepped together: their states stay in registers and the first-level cache
BLOCK = 64

#: columns of the per-set drive-train table ``drive_table``
DRIVE_COLUMNS = (
    *('wheel_mass', 'wheel_radius', 'wheel_inertia', 'reflected_rotor_inertia', 'gravity'),
    *('sin_slope', 'cos_slope', 'viscous_friction', 'coulomb_friction', 'ground_viscous'),
    *('caster_contact_pitch', 'caster_stiffness', 'caster_damping'),
)


def drive_table(drives) -> np.ndarray:
    """(P, len(DRIVE_COLUMNS)) the drive trains' fields as the compiled loop reads them."""
    trig = {'sin_slope': math.sin, 'cos_slope': math.cos}
    rows = [
        [trig[n](d.floor_slope) if n in trig else getattr(d, n) for n in DRIVE_COLUMNS]
        for d in drives
    ]
    return np.array(rows, float).reshape(-1, len(DRIVE_COLUMNS))


#: |x| beyond which tanh(x) is 1 to double precision (tanh(19.1) = 1 - 5e-17)
_TANH_SATURATION = 20.0


def simd_tanh(x):
    """tanh(x) from multiplies, adds and one division, without loops or calls, so that a
    compiled loop over elements runs it in SIMD lanes (a libm tanh is one call per element, as
    slow as the rest of a sub-step): m = e^(2|x|) - 1 as the Taylor series of e^v - 1 to v^16/16!
    at v = 2|x|/64 <= 0.625 (truncation below 1e-16) and six doublings (e^2v - 1 = m (m + 2),
    which keeps the relative accuracy near 0), then tanh = m / (m + 2). Within 4 ulp of tanh."""
    a = abs(x)
    big = a > _TANH_SATURATION
    v = (a * (1.0 - big) + _TANH_SATURATION * big) * (2.0 / 64.0)
    m = 1.0 / 20922789888000.0  # 1/16!
    m = m * v + 1.0 / 1307674368000.0
    m = m * v + 1.0 / 87178291200.0
    m = m * v + 1.0 / 6227020800.0
    m = m * v + 1.0 / 479001600.0
    m = m * v + 1.0 / 39916800.0
    m = m * v + 1.0 / 3628800.0
    m = m * v + 1.0 / 362880.0
    m = m * v + 1.0 / 40320.0
    m = m * v + 1.0 / 5040.0
    m = m * v + 1.0 / 720.0
    m = m * v + 1.0 / 120.0
    m = m * v + 1.0 / 24.0
    m = m * v + 1.0 / 6.0
    m = m * v + 1.0 / 2.0
    m = (m * v + 1.0) * v
    m = m * (m + 2.0)  # e^(2v) - 1, six times: e^(64 v) - 1
    m = m * (m + 2.0)
    m = m * (m + 2.0)
    m = m * (m + 2.0)
    m = m * (m + 2.0)
    m = m * (m + 2.0)
    t = m / (m + 2.0)
    return t - 2.0 * t * (x < 0.0)


# what the equations call, compiled where they call it
register_jitable(inline='always', error_model='numpy')(caster_torque)
overload(smooth_sign, inline='always')(lambda x: register_jitable(simd_tanh))
_equations = njit(inline='always', error_model='numpy')(pitch_equations)
_terms = njit(inline='always', error_model='numpy')(body_terms)
_adjusted = njit(inline='always', error_model='numpy')(adjusted_body)
_euler = njit(inline='always', error_model='numpy')(semi_implicit_euler)


@njit(inline='always')
def _rotate(s, c, delta):
    """(sin, cos) of an angle advanced by a small `delta`, from theirs."""
    d2 = delta * delta
    sd = ((d2 * (1.0 / 120.0) - 1.0 / 6.0) * d2 + 1.0) * delta
    cm = ((d2 * (-1.0 / 720.0) + 1.0 / 24.0) * d2 - 0.5) * d2
    return s + (s * cm + c * sd), c + (c * cm - s * sd)


#: the physics' source: numba keys its on-disk cache on this file and on the cells of a closure,
#: not on the modules a function calls into, so the hash of krang_model.wip goes into the key
PHYSICS = hashlib.sha256(Path(wip.__file__).read_bytes()).hexdigest()


def _compile(physics: str):
    """The batch loop, compiled on first use and cached on disk under a key that holds `physics`
    (a change of ``krang_model.wip`` compiles it again, about 1.5 s)."""

    @njit(nogil=True, cache=True, error_model='numpy')
    def integrate(
        state, trig, j0, j1, dt, anchor,
        mass, dist, offset, inertia, body_index,
        torque, torque_index, torque_scale, com_shift, inertia_add, drive,
        f_phi, f_qbase, record_slot, record,
    ):  # fmt: skip
        """Step every element (p, s) from sub-step j0 to j1, in place.

        state (P, S, 4) [phi, q_base, phi', q_base'] and trig (P, S, 2) [sin, cos of theta],
        carried between calls; dt the sub-step; anchor: exact sines and cosines at sub-steps
        j % anchor == 0. Bodies: mass (U,), dist / offset / inertia (U, S, Jb) at each
        sub-step's mid-point (Jb = 1: a still body), body_index (P,) the variant of each set;
        torque (D, S, J) the mean total wheel torque over each sub-step, torque_index (P,) and
        torque_scale (P,) each set's delay variant and applied/commanded factor; com_shift,
        inertia_add (P,) (``adjusted_body``); drive (P, C) (``drive_table``); f_phi, f_qbase
        (P, S) extra generalised forces held over the call. record_slot (J + 1,): the slot of
        ``record`` (P, S, R, 4) that receives the state after each sub-step (-1: none).

        The tables are window-major, so a block's sub-steps are one stretch of memory; each
        sub-step first gathers the block's inputs into rows of one work array, then steps the
        block on those rows alone (a loop the compiler turns into SIMD instructions)."""
        physics  # a cell of the closure, so part of the on-disk cache's key
        n_sets, n_win = state.shape[0], state.shape[1]
        last_body = dist.shape[2] - 1
        # rows: phi, q_base, phi', q_base', sin, cos, torque, distance, inertia, offset, its
        # change, f_phi, f_qbase
        w = np.empty(13 * BLOCK)
        for p in range(n_sets):
            u, di = body_index[p], torque_index[p]
            m = mass[u]
            mw, r, iw, rotor, g = drive[p, 0], drive[p, 1], drive[p, 2], drive[p, 3], drive[p, 4]
            sin_sl, cos_sl, visc, coul, ground = (
                drive[p, 5],
                drive[p, 6],
                drive[p, 7],
                drive[p, 8],
                drive[p, 9],
            )
            cp, ck, cc = drive[p, 10], drive[p, 11], drive[p, 12]
            dl, ia, ts = com_shift[p], inertia_add[p], torque_scale[p]
            tq, ds, it, of = torque[di], dist[u], inertia[u], offset[u]
            for s0 in range(0, n_win, BLOCK):
                n = min(BLOCK, n_win - s0)
                for b in range(n):
                    for c in range(4):
                        w[c * BLOCK + b] = state[p, s0 + b, c]
                    w[4 * BLOCK + b] = trig[p, s0 + b, 0]
                    w[5 * BLOCK + b] = trig[p, s0 + b, 1]
                    w[11 * BLOCK + b] = f_phi[p, s0 + b]
                    w[12 * BLOCK + b] = f_qbase[p, s0 + b]
                for j in range(j0, j1):
                    jb = min(j, last_body)
                    jn = min(j + 1, last_body)
                    for b in range(n):
                        s = s0 + b
                        w[6 * BLOCK + b] = tq[s, j] * ts
                        w[7 * BLOCK + b] = ds[s, jb]
                        w[8 * BLOCK + b] = it[s, jb]
                        w[9 * BLOCK + b] = of[s, jb]
                        w[10 * BLOCK + b] = of[s, jn] - of[s, jb]
                    if j % anchor == 0:
                        for b in range(n):
                            theta = w[BLOCK + b] + w[9 * BLOCK + b]
                            w[4 * BLOCK + b] = math.sin(theta)
                            w[5 * BLOCK + b] = math.cos(theta)
                    for b in range(n):
                        dist_b, inertia_b = _adjusted(
                            m, w[7 * BLOCK + b], w[8 * BLOCK + b], dl, ia
                        )
                        m11, mrl, m22, m11m22, mgl, grade = _terms(
                            m, dist_b, inertia_b, mw, r, iw, rotor, g, sin_sl
                        )
                        st, ct = w[4 * BLOCK + b], w[5 * BLOCK + b]
                        q0 = w[BLOCK + b]
                        ddphi, ddqb = _equations(
                            q0, w[2 * BLOCK + b], w[3 * BLOCK + b], w[6 * BLOCK + b],
                            w[11 * BLOCK + b], w[12 * BLOCK + b],
                            st, st * cos_sl + ct * sin_sl, ct * cos_sl - st * sin_sl,
                            m11, mrl, m22, m11m22, mgl, grade, rotor, visc, coul, ground,
                            cp, ck, cc,
                        )  # fmt: skip
                        phi, qb, dphi, dqb = _euler(
                            w[b], q0, w[2 * BLOCK + b], w[3 * BLOCK + b], ddphi, ddqb, dt
                        )
                        w[b] = phi
                        w[BLOCK + b] = qb
                        w[2 * BLOCK + b] = dphi
                        w[3 * BLOCK + b] = dqb
                        sn, cs = _rotate(st, ct, qb - q0 + w[10 * BLOCK + b])
                        w[4 * BLOCK + b] = sn
                        w[5 * BLOCK + b] = cs
                    slot = record_slot[j + 1]
                    if slot >= 0:
                        for b in range(n):
                            for c in range(4):
                                record[p, s0 + b, slot, c] = w[c * BLOCK + b]
                for b in range(n):
                    for c in range(4):
                        state[p, s0 + b, c] = w[c * BLOCK + b]
                    trig[p, s0 + b, 0] = w[4 * BLOCK + b]
                    trig[p, s0 + b, 1] = w[5 * BLOCK + b]

    return integrate


integrate = _compile(PHYSICS)
