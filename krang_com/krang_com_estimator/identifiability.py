"""What balanced poses can and cannot tell about beta: rank and base parameters of the regressor.

Method (Gautier & Khalil 1990; docs/learning.md, "What balanced poses can and cannot tell"): stack
phi(q)^T for many random configurations into Phi (N x 92) and run a QR decomposition with column
pivoting, Phi P = Q R. The numerical rank r is the number of base parameters. With
R = [[R11, R12], [0, 0]] the first r pivoted columns are independent and every other parameter only
acts through the base combination
    beta_base = beta_1 + R11^-1 R12 beta_2,
so beta_2 (the dependent parameters) can be moved freely along the null space of Phi.

Three regressors are compared:
- arbitrary configurations (random joints AND random base pitch): the x row of the CoM alone;
- balanced poses (q_base = the balance pitch of the real beta, what the robot actually gives us):
  phi(q)^T beta_real = 0 for every row, so beta_real itself is in the null space: one direction
  fewer, the overall scale of the mass moments;
- the same balanced rows plus the known total mass (a row of ones on the mass entries): it does NOT
  restore the scale, because the Base and wheel masses never appear in phi (their origins are on
  the axle), so they can absorb any change of total mass; and knowing all masses does not either,
  because every other mass acts like moments of the links it hangs on.

For one fit (krang learn), information_directions / determined_report say which directions of
beta its poses determine and which its prior sets: the generalised eigenproblem of the data's
information against the prior's.
"""

import numpy as np
from scipy.linalg import qr

from krang_model.com import balance_pitch, phi as phi_rows
from krang_model.robot import load_krang

AXES = {1: 'x', 2: 'y', 3: 'z'}


def describe_entry(robot, j):
    """Human name of beta entry j, e.g. 'L6 m*y' or 'Base m*x (axle direction)'."""
    body, k = robot.body_names[j // 4], j % 4
    if k == 0:
        return f'{body} m'
    return f'{body} m*{AXES[k]}'


def sample_regressor(robot=None, n=2000, seed=0, mode='balanced', beta_real=None, pool=None):
    """Stacked phi rows (n, n_beta). mode 'balanced': random pool joints at the balance pitch of
    beta_real; 'arbitrary': random joints and a random base pitch in [-pi/2, pi/2].
    `pool` = (q_base, joints) to use given poses instead of sampling joints uniformly."""
    robot = robot or load_krang()
    rng = np.random.default_rng(seed)
    if pool is not None:
        q_base, joints = pool
        joints = np.asarray(joints)[:n]
        q_base = np.asarray(q_base)[:n]
    else:
        from krang_pose_server.pool import pool_config

        cfg = pool_config()
        joints = rng.uniform(
            cfg['sampling_lower'], cfg['sampling_upper'], size=(n, len(robot.pose_joints))
        )
        q_base = None
    beta_real = robot.nominal_beta if beta_real is None else np.asarray(beta_real, dtype=float)
    if mode == 'balanced':
        q_base = balance_pitch(robot, joints, beta_real)
    elif mode == 'arbitrary':
        q_base = rng.uniform(-np.pi / 2, np.pi / 2, size=len(joints))
    elif q_base is None:
        raise ValueError(f'mode must be balanced or arbitrary, not {mode!r}')
    return phi_rows(robot, q_base, joints)


def base_parameters(Phi, rtol=1e-9, order=None):
    """Base parameters of Phi. Returns dict: rank, independent (column indices), dependent,
    coefficients (r x d: beta_base = beta_indep + coef @ beta_dep, i.e. Phi[:, dep] = Phi[:, indep]
    @ coef), zero (columns that are 0), diag (|R_kk| of the pivoted QR).

    The rank is that of the QR with column pivoting. Which columns count as independent is chosen
    greedily in `order` (a preference, e.g. proximal bodies and moments first, so that a distal
    mass is explained by the moments of the link it hangs on); without `order` the QR pivots are
    used."""
    Phi = np.asarray(Phi, dtype=float)
    n = Phi.shape[1]
    col_norm = np.linalg.norm(Phi, axis=0)
    scale = col_norm.max()
    zero = [int(j) for j in np.flatnonzero(col_norm <= rtol * scale)]
    _, R, piv = qr(Phi, mode='economic', pivoting=True)
    d = np.abs(np.diag(R))
    rank = int((d > rtol * d[0]).sum())
    if order is None:
        indep = [int(j) for j in piv[:rank]]
    else:
        indep = []
        basis = np.zeros((Phi.shape[0], 0))
        for j in order:
            if j in zero or len(indep) == rank:
                continue
            col = Phi[:, j]
            res = col - basis @ (basis.T @ col)
            if np.linalg.norm(res) > 1e-7 * max(col_norm[j], rtol * scale):
                indep.append(int(j))
                basis = np.column_stack([basis, res / np.linalg.norm(res)])
        if len(indep) != rank:
            raise RuntimeError(
                f'preferred-order selection found {len(indep)} columns, QR rank {rank}'
            )
    dep = [j for j in range(n) if j not in indep]
    coef = (
        np.linalg.lstsq(Phi[:, indep], Phi[:, dep], rcond=None)[0] if dep else np.zeros((rank, 0))
    )
    return {
        'rank': rank,
        'n_params': n,
        'independent': indep,
        'dependent': dep,
        'coefficients': coef,
        'zero': zero,
        'diag': d,
    }


def preferred_order(robot):
    """Bodies in the authors' order (proximal first within each arm), moments before masses."""
    order = []
    for i in range(robot.n_bodies):
        order += [4 * i + 1, 4 * i + 2, 4 * i + 3]
    for i in range(robot.n_bodies):
        order.append(4 * i)
    return order


def analyse(robot=None, n=2000, seed=0, beta_real=None, pool=None, coef_tol=1e-6):
    """The full report as a dict (JSON-friendly) plus human-readable lines under 'lines'."""
    robot = robot or load_krang()
    beta_real = robot.nominal_beta if beta_real is None else np.asarray(beta_real, dtype=float)
    phi_arb = sample_regressor(robot, n, seed, 'arbitrary', beta_real, pool)
    phi_bal = sample_regressor(robot, n, seed, 'balanced', beta_real, pool)
    mass_row = np.zeros(robot.n_beta)
    mass_row[0::4] = 1.0
    order = preferred_order(robot)
    arb = base_parameters(phi_arb, order=order)
    bal = base_parameters(phi_bal)
    bal_mass = base_parameters(np.vstack([phi_bal, mass_row * np.abs(phi_bal).max()]))
    moments = [j for j in range(robot.n_beta) if j % 4]
    bal_known_m = base_parameters(phi_bal[:, moments])
    arb_known_m = base_parameters(phi_arb[:, moments])
    # The scale direction: beta_real with the Base mass lowered to keep the total mass.
    base_m = robot.body_names.index('Base') * 4
    v = beta_real.copy()
    v[base_m] -= beta_real[0::4].sum()
    scale_residual = float(
        np.linalg.norm(phi_bal @ v) / (np.linalg.norm(phi_bal) * np.linalg.norm(v))
    )
    scale_seen_arbitrary = float(
        np.linalg.norm(phi_arb @ v) / (np.linalg.norm(phi_arb) * np.linalg.norm(v))
    )

    name = lambda j: describe_entry(robot, j)  # noqa: E731
    lines = [
        f'Regressor of x_com over {n} random configurations, {robot.n_beta} parameters '
        f'({robot.n_bodies} bodies x [m, m*x, m*y, m*z]):',
        f'  arbitrary configurations (random base pitch): rank {arb["rank"]}',
        f'  balanced poses (phi^T beta = 0):              rank {bal["rank"]}',
        f'  balanced + known total mass:                  rank {bal_mass["rank"]}',
        f'  masses known, moments only ({len(moments)}): rank {bal_known_m["rank"]} balanced, '
        f'{arb_known_m["rank"]} arbitrary',
        f'So at most {arb["rank"]} combinations of the {robot.n_beta} numbers can ever be learned '
        f'from x_com; '
        f'the other {robot.n_beta - arb["rank"]} directions stay where the prior puts them.',
        '',
        'Not identifiable at all:',
    ]
    for j in arb['zero']:
        lines.append(f'  {name(j)}{_why_zero(robot, j)}: not identifiable — phi is always 0')
    # dependency groups: connected components of (dependent parameter, its partners)
    coef = arb['coefficients']
    links = {}
    combos = []
    for c, j in enumerate(arb['dependent']):
        if j in arb['zero']:
            continue
        colmax = max(np.abs(coef[:, c]).max(), 1e-300)
        partners = [
            (arb['independent'][k], float(coef[k, c]))
            for k in range(arb['rank'])
            if abs(coef[k, c]) > coef_tol * max(1.0, colmax)
        ]
        partners.sort(key=lambda t: -abs(t[1]))
        combos.append({'parameter': name(j), 'acts_like': [(name(k), v) for k, v in partners]})
        links[j] = [k for k, _ in partners]
    groups = _components(links)
    lines += [
        '',
        'Identifiable only in combination (d in the first parameter acts on every x_com exactly '
        'like '
        'the listed changes of the others, so the data cannot tell them apart):',
    ]
    for combo in combos:
        text = ' '.join(
            f'{"+" if v >= 0 else "-"} {abs(v):.3g} {k}' for k, v in combo['acts_like'][:6]
        )
        more = (
            '' if len(combo['acts_like']) <= 6 else f' (+{len(combo["acts_like"]) - 6} more terms)'
        )
        lines.append(f'  {combo["parameter"]}: acts like {text}{more}')
    lines += [
        '',
        'Groups (parameters tied together; only "identifiable" combinations of each group are '
        'learned):',
    ]
    group_out = []
    for g in groups:
        n_dep = sum(1 for j in g if j in links)
        group_out.append(
            {
                'parameters': [name(j) for j in sorted(g)],
                'identifiable_combinations': len(g) - n_dep,
            }
        )
        lines.append(f'  {len(g) - n_dep} of {len(g)}: ' + ', '.join(name(j) for j in sorted(g)))
    lines += [
        '',
        f'Balanced poses lose {arb["rank"] - bal["rank"]} more direction: the data only say '
        'phi^T beta = 0, so beta and c*beta fit equally well (the real beta is in their null '
        'space).',
        'The known total mass does not remove it: beta_real with the Base mass lowered by the '
        'total '
        f'mass is still invisible to balanced poses (relative residual {scale_residual:.1e}, '
        f'against '
        f'{scale_seen_arbitrary:.1e} at arbitrary pitch), because the Base and wheel masses never '
        'appear in phi. Knowing every mass does not remove it either (moments only: rank '
        f'{bal_known_m["rank"]} balanced against {arb_known_m["rank"]} arbitrary): each mass acts '
        'like moments of the links it hangs on (list above), so the effective moments can still '
        'be '
        'scaled. The scale of the mass moments (how far the CoM is from the axle, i.e. the CoM '
        'height at balance) is therefore set by the prior; the CoM direction (what balancing '
        'needs) '
        'is what the data determine.',
    ]
    return {
        'n_configurations': n,
        'n_params': robot.n_beta,
        'rank_arbitrary': arb['rank'],
        'rank_balanced': bal['rank'],
        'rank_balanced_with_total_mass': bal_mass['rank'],
        'rank_moments_masses_known_balanced': bal_known_m['rank'],
        'rank_moments_masses_known_arbitrary': arb_known_m['rank'],
        'n_moment_params': len(moments),
        'scale_direction_residual_balanced': scale_residual,
        'scale_direction_residual_arbitrary': scale_seen_arbitrary,
        'unidentifiable': [name(j) for j in arb['zero']],
        'combinations': combos,
        'groups': group_out,
        'lines': lines,
    }


def _components(links):
    """Connected components of the undirected graph given as {node: [neighbours]}."""
    adj = {}
    for a, bs in links.items():
        for b in bs:
            adj.setdefault(a, set()).add(b)
            adj.setdefault(b, set()).add(a)
    seen, out = set(), []
    for start in adj:
        if start in seen:
            continue
        stack, comp = [start], set()
        while stack:
            x = stack.pop()
            if x in comp:
                continue
            comp.add(x)
            stack.extend(adj[x] - comp)
        seen |= comp
        out.append(comp)
    return sorted(out, key=lambda g: min(g))


def _why_zero(robot, j):
    k = j % 4
    if k == 1:
        return ' (axle direction)'
    if k == 0:
        return ' (its origin is on the axle)'
    return ''


# ---------------------------------------------- what a fit's data determine, and what its prior
#: a direction counts as determined by the data when they hold at least as much information on it
#: as the prior (its posterior variance is at most half the prior's)
DETERMINED_RATIO = 1.0


def information_directions(prior_std, rows, var, A=None):
    """The directions of beta ranked by how much the data say about them against the prior:
    (lam, V, Z, H0) with D V = H0 V diag(lam), V^T H0 V = I, where H0 = Z^T P0^-1 Z is the prior's
    and D = (G Z)^T R^-1 (G Z) the data's information on the null space Z of the equality
    constraints A (rows G, variances R: the fit's linear rows). lam_k is the data-to-prior
    information ratio of direction Z v_k: posterior variance / prior variance = 1 / (1 + lam_k).
    The coordinate of a change d (A d = 0) along v_k is v_k^T H0 Z^T d."""
    from scipy.linalg import eigh

    from .solvers import null_space

    prior_std = np.asarray(prior_std, dtype=float)
    n = len(prior_std)
    Z = null_space(np.zeros((0, n)) if A is None else np.atleast_2d(A), n)
    H0 = Z.T @ (Z / prior_std[:, None] ** 2)
    GZ = np.atleast_2d(rows) @ Z
    D = GZ.T @ (GZ / np.asarray(var, dtype=float)[:, None])
    lam, V = eigh(0.5 * (D + D.T), 0.5 * (H0 + H0.T))
    order = np.argsort(lam)[::-1]
    return np.clip(lam[order], 0.0, None), V[:, order], Z, H0


def determined_report(robot, prior_std, rows, var, A=None, threshold=DETERMINED_RATIO):
    """Which directions and entries of beta a fit's data determine and which come from its prior
    (JSON-friendly). Directions: information_directions with lam >= threshold. Entries: the
    posterior std of each entry over its prior std (prior conditioned on A); an entry counts as
    from the data when that ratio is at most 1/sqrt(1 + threshold), as fixed when the constraints
    alone fix it."""
    lam, V, Z, H0 = information_directions(prior_std, rows, var, A)
    k = int((lam >= threshold).sum())
    HV = H0 @ V  # the data's information D = (H0 V) diag(lam) (H0 V)^T
    prior_var = np.einsum('ij,jk,ik->i', Z, np.linalg.inv(H0), Z)
    post_var = np.einsum('ij,jk,ik->i', Z, np.linalg.inv(H0 + (HV * lam) @ HV.T), Z)
    fixed = prior_var <= 1e-12 * prior_var.max()
    ratio = np.sqrt(np.where(fixed, 1.0, post_var / np.where(fixed, 1.0, prior_var)))
    cut = 1.0 / np.sqrt(1.0 + threshold)
    labels = [describe_entry(robot, j) for j in range(robot.n_beta)]
    zero = np.flatnonzero(np.abs(np.atleast_2d(rows)).max(0) == 0)
    per_body = {}
    for i, body in enumerate(robot.body_names):
        per_body[body] = {
            q: (None if fixed[4 * i + c] else round(float(ratio[4 * i + c]), 3))
            for c, q in enumerate(('m', 'm*x', 'm*y', 'm*z'))
        }
    return {
        'directions': int(len(lam)),
        'determined_by_data': k,
        'from_prior': int(len(lam)) - k,
        'threshold_information_ratio': float(threshold),
        'information_ratios_top': [round(float(v), 3) for v in lam[: max(k, 1) + 3]],
        'entries_from_data': [
            labels[j] for j in range(robot.n_beta) if not fixed[j] and ratio[j] <= cut
        ],
        'entries_fixed_by_constraints': [labels[j] for j in np.flatnonzero(fixed)],
        'entries_never_seen': [labels[j] for j in zero if not fixed[j]],
        'posterior_over_prior_std': per_body,
    }
