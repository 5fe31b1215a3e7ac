"""Priors and physical constraints of beta: the prior spread, the hard linear constraints (known
total mass, wheel CoMs on the axle), the plausible region of every body (its mass within a stated
spread of the URDF's, its CoM inside its link's inflated collision box and within a stated radius
of the CAD CoM), and the consistency check of a learned beta."""

import math
import xml.etree.ElementTree as ET

import numpy as np


def physical_prior_std(robot, beta0=None, mass_frac=0.1, com_std=0.03, mass_floor=1e-3):
    """Prior std per beta entry from physical plausibility: each mass known to `mass_frac`
    (relative, at least `mass_floor` kg), each CoM coordinate to `com_std` metres. For the moment
    m*c with m and c independent: var(m c) = (m s_c)^2 + (c s_m)^2 + (s_m s_c)^2."""
    beta0 = robot.nominal_beta if beta0 is None else np.asarray(beta0, dtype=float)
    std = np.empty_like(beta0)
    for i in range(robot.n_bodies):
        m = beta0[4 * i]
        c = beta0[4 * i + 1 : 4 * i + 4] / m if m != 0 else np.zeros(3)
        s_m = max(mass_frac * abs(m), mass_floor)
        std[4 * i] = s_m
        std[4 * i + 1 : 4 * i + 4] = np.sqrt(
            (m * com_std) ** 2 + (c * s_m) ** 2 + (s_m * com_std) ** 2
        )
    return std


def recipe_prior_std(beta0, max_deviation=0.5, max_offset=0.5, mass_std=1e-6):
    """Prior std matching the authors' erroneous-beta recipe (masses exact; v + U(-d,d) v +
    U(-o,o)): var = (d^2 v^2 + o^2) / 3 per moment entry, with v taken as the start value."""
    beta0 = np.asarray(beta0, dtype=float)
    std = np.sqrt((max_deviation**2 * beta0**2 + max_offset**2) / 3.0)
    std[0::4] = mass_std
    return std


def equality_constraints(robot, total_mass=None, wheels_on_axle=True):
    """(A, b) of the hard linear constraints A beta = b: sum of masses = total_mass (if given) and
    each wheel's m*y = m*z = 0 (its CoM on its own axis, which is the axle; the wheel frame's x
    axis is the axle)."""
    rows, rhs = [], []
    if total_mass is not None:
        a = np.zeros(robot.n_beta)
        a[0::4] = 1.0
        rows.append(a)
        rhs.append(float(total_mass))
    if wheels_on_axle:
        for w in robot.wheel_body_ids:
            for k in (2, 3):
                a = np.zeros(robot.n_beta)
                a[4 * w + k] = 1.0
                rows.append(a)
                rhs.append(0.0)
    if not rows:
        return np.zeros((0, robot.n_beta)), np.zeros(0)
    return np.array(rows), np.array(rhs)


def com_bounds(robot, inflate=0.05):
    """Plausible CoM region of every body, in its own frame: the axis-aligned bounding box of its
    URDF collision shape grown by `inflate` metres on every side, and always containing the CAD CoM
    (grown likewise). Bodies without collision geometry (the gripper plates) get the box of
    `inflate` around the CAD CoM. Returns (lo, hi) arrays (n_bodies, 3)."""
    root = ET.parse(robot.urdf_path).getroot()
    lo = np.empty((robot.n_bodies, 3))
    hi = np.empty((robot.n_bodies, 3))
    beta0 = robot.nominal_beta
    for i, name in enumerate(robot.body_names):
        cad = beta0[4 * i + 1 : 4 * i + 4] / beta0[4 * i]
        box_lo, box_hi = cad.copy(), cad.copy()
        for col in root.findall(f"link[@name='{name}']/collision"):
            corners = _shape_corners(col)
            if corners is not None:
                box_lo = np.minimum(box_lo, corners.min(0))
                box_hi = np.maximum(box_hi, corners.max(0))
        lo[i], hi[i] = box_lo - inflate, box_hi + inflate
    return lo, hi


def _shape_corners(col):
    origin = col.find('origin')
    xyz = (
        np.zeros(3)
        if origin is None
        else np.array([float(v) for v in origin.get('xyz', '0 0 0').split()])
    )
    rpy = (
        np.zeros(3)
        if origin is None
        else np.array([float(v) for v in origin.get('rpy', '0 0 0').split()])
    )
    geom = col.find('geometry')
    if geom.find('box') is not None:
        half = np.array([float(v) for v in geom.find('box').get('size').split()]) / 2
    elif geom.find('cylinder') is not None:
        r = float(geom.find('cylinder').get('radius'))
        half = np.array([r, r, float(geom.find('cylinder').get('length')) / 2])
    elif geom.find('sphere') is not None:
        half = np.full(3, float(geom.find('sphere').get('radius')))
    else:
        return None
    signs = np.array(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float
    )
    return xyz + (signs * half) @ _rpy(rpy).T


def _rpy(rpy):
    r, p, y = rpy
    cx, sx, cy, sy, cz, sz = (
        math.cos(r),
        math.sin(r),
        math.cos(p),
        math.sin(p),
        math.cos(y),
        math.sin(y),
    )
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


#: the plausible region of a learned body (docs/learning.md, "Plausible masses and CoMs"): its mass
#: within MASS_SPREAD of the URDF's (cabling, fasteners and electronics CAD leaves out), its CoM
#: within COM_RADIUS_M of the CAD CoM. Physical statements, not fitted to any data.
MASS_SPREAD = 0.2
COM_RADIUS_M = 0.08
#: bodies lighter than this (the gripper plates, 1e-5 kg in the URDF) only keep m >= 0 and the box
PLAUSIBLE_MIN_MASS_KG = 0.1


def mass_bounds(robot, spread=MASS_SPREAD):
    """(lo, hi) (n_bodies,) plausible masses: the URDF's nominal mass times (1 -+ spread); (0, inf)
    for bodies lighter than PLAUSIBLE_MIN_MASS_KG."""
    m0 = robot.nominal_beta[0::4]
    heavy = m0 >= PLAUSIBLE_MIN_MASS_KG
    lo = np.where(heavy, m0 * (1.0 - spread), 0.0)
    hi = np.where(heavy, m0 * (1.0 + spread), np.inf)
    return lo, hi


def com_balls(robot, radius=COM_RADIUS_M):
    """(ids, centres (k, 3), radius): the bodies whose CoM must stay within `radius` m of the CAD
    CoM (all but those lighter than PLAUSIBLE_MIN_MASS_KG), for solvers.map_constrained."""
    beta0 = robot.nominal_beta
    ids = np.flatnonzero(beta0[0::4] >= PLAUSIBLE_MIN_MASS_KG)
    centres = np.array([beta0[4 * i + 1 : 4 * i + 4] / beta0[4 * i] for i in ids])
    return ids, centres, float(radius)


def inequality_constraints(robot, bounds=None, min_mass=0.0, mass_spread=None):
    """(G, h) with G beta >= h: every mass >= min_mass (and, with mass_spread, within
    mass_bounds) and every CoM coordinate inside its bounds, written linearly as
    m*c - lo*m >= 0 and hi*m - m*c >= 0."""
    lo, hi = com_bounds(robot) if bounds is None else bounds
    m_lo, m_hi = mass_bounds(robot, mass_spread) if mass_spread is not None else (None, None)
    rows, rhs = [], []
    for i in range(robot.n_bodies):
        a = np.zeros(robot.n_beta)
        a[4 * i] = 1.0
        rows.append(a)
        rhs.append(min_mass if m_lo is None else max(min_mass, m_lo[i]))
        if m_hi is not None and np.isfinite(m_hi[i]):
            rows.append(-a)
            rhs.append(-m_hi[i])
        for k in range(3):
            a = np.zeros(robot.n_beta)
            a[4 * i + 1 + k], a[4 * i] = 1.0, -lo[i, k]
            rows.append(a)
            rhs.append(0.0)
            a = np.zeros(robot.n_beta)
            a[4 * i + 1 + k], a[4 * i] = -1.0, hi[i, k]
            rows.append(a)
            rhs.append(0.0)
    return np.array(rows), np.array(rhs)


def physical_consistency(
    robot, beta, total_mass=None, bounds=None, tol=1e-6, mass_spread=None, com_radius=None
):
    """Checks a beta for physical consistency. Returns a dict: ok, and the list of violations
    (negative masses, total mass off, CoMs outside their bounds, wheel CoMs off the axle; with
    mass_spread / com_radius also masses outside mass_bounds and CoMs farther than com_radius
    from CAD), plus the CoM of every body, its distance from the CAD CoM, and `at_bound`: the
    plausibility bounds the beta touches (where the data push against the prior's region)."""
    beta = np.asarray(beta, dtype=float)
    lo, hi = com_bounds(robot) if bounds is None else bounds
    m_lo, m_hi = mass_bounds(robot, mass_spread) if mass_spread is not None else (None, None)
    ball_ids = set(com_balls(robot)[0].tolist()) if com_radius is not None else set()
    at_bound = []
    total_mass = robot.nominal_mass if total_mass is None else total_mass
    violations = []
    bodies = []
    cad = robot.nominal_beta
    for i, name in enumerate(robot.body_names):
        m = beta[4 * i]
        com = beta[4 * i + 1 : 4 * i + 4] / m if m != 0 else np.full(3, np.nan)
        com_cad = cad[4 * i + 1 : 4 * i + 4] / cad[4 * i]
        moved = float(np.linalg.norm(com - com_cad))
        bodies.append(
            {
                'name': name,
                'mass': float(m),
                'com': com.tolist(),
                'com_moved_m': moved,
                'mass_change_kg': float(m - cad[4 * i]),
            }
        )
        if not m > 0:
            violations.append(f'{name}: mass {m:.4g} kg is not positive')
            continue
        if m_lo is not None and np.isfinite(m_hi[i]):
            bodies[-1]['mass_range_kg'] = [float(m_lo[i]), float(m_hi[i])]
            if m < m_lo[i] * (1 - 1e-6) or m > m_hi[i] * (1 + 1e-6):
                violations.append(
                    f'{name}: mass {m:.3f} kg outside its plausible range '
                    f'[{m_lo[i]:.3f}, {m_hi[i]:.3f}] kg'
                )
            elif min(m - m_lo[i], m_hi[i] - m) < 1e-3 * m_hi[i]:
                at_bound.append(f'{name} mass')
        if i in ball_ids:
            if moved > com_radius + 1e-6:
                violations.append(
                    f'{name}: CoM {100 * moved:.2f} cm from CAD, beyond {100 * com_radius:.1f} cm'
                )
            elif moved > com_radius - 1e-4:
                at_bound.append(f'{name} CoM')
        out = (com < lo[i] - tol) | (com > hi[i] + tol)
        if out.any():
            violations.append(
                f'{name}: CoM {np.round(com, 4).tolist()} m outside its plausible box '
                f'[{np.round(lo[i], 3).tolist()}, {np.round(hi[i], 3).tolist()}]'
            )
    for w in robot.wheel_body_ids:
        off = np.abs(beta[4 * w + 2 : 4 * w + 4])
        if off.max() > tol:
            violations.append(
                f'{robot.body_names[w]}: CoM off the axle (m*y, m*z = '
                f'{beta[4 * w + 2]:.3g}, {beta[4 * w + 3]:.3g} kg m)'
            )
    mass = float(beta[0::4].sum())
    if abs(mass - total_mass) > 1e-6 * total_mass:
        violations.append(f'total mass {mass:.3f} kg instead of {total_mass:.3f} kg')
    return {
        'ok': not violations,
        'violations': violations,
        'total_mass': mass,
        'bodies': bodies,
        'at_bound': at_bound,
    }


def com_shift_std(robot, beta, covariance, reference=None):
    """Posterior std (m) of how far each body's CoM moved from `reference` (default CAD), by the
    delta method: c = (m c)/m, J = [-(m c)/m^2, I/m], var(c) = J Sigma_body J^T, projected on the
    direction of the shift (the whole 3-d std where the CoM did not move). (n_bodies,) array."""
    beta = np.asarray(beta, dtype=float)
    ref = robot.nominal_beta if reference is None else np.asarray(reference, dtype=float)
    out = np.empty(robot.n_bodies)
    for i in range(robot.n_bodies):
        m, mc = beta[4 * i], beta[4 * i + 1 : 4 * i + 4]
        J = np.column_stack([-mc / m**2, np.eye(3) / m])
        cov = J @ covariance[4 * i : 4 * i + 4, 4 * i : 4 * i + 4] @ J.T
        d = mc / m - ref[4 * i + 1 : 4 * i + 4] / ref[4 * i]
        norm = np.linalg.norm(d)
        out[i] = (
            math.sqrt(max(d @ cov @ d / norm**2, 0.0))
            if norm > 1e-9
            else math.sqrt(max(np.trace(cov), 0.0))
        )
    return out
