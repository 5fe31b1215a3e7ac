"""Erroneous betas: the hypotheses the pose filter learns on, and the start points of simulated
learning.

Two recipes, both vectorised (a whole batch is drawn at once, the rejects are redrawn):
- `authors_betas` (docs/learning.md; 18c filter_training_set.cpp createPriorBeta): masses
  unchanged; every m*x, m*y, m*z entry v becomes v + U(-dev, dev) v + U(-off, off) [kg m] (dev =
  off = 0.5); a beta is redrawn until |x_com| = |phi(first pose)^T beta| > min_xcom (2 cm) at the
  first pose of the pool.
- `paper_betas` (paper §III-A, the Matlab 7-link study): 20 % noise on m, m*x and m*y, i.e.
  v := v (1 + U(-f, f)) with f = 0.2 for those entries (m*z untouched), optionally with the same
  minimum-error rejection.
"""

import numpy as np

from krang_model.config import load_config


def erroneous_config():
    return dict(load_config('poses.yaml')['pose_server']['ros__parameters']['erroneous_betas'])


def _rejection_sample(draw, n, first_phi, min_xcom, rng, max_rounds=1000):
    out = []
    got = 0
    for _ in range(max_rounds):
        batch = draw(max(2 * (n - got), 64))
        if first_phi is not None and min_xcom > 0:
            batch = batch[np.abs(batch @ first_phi) > min_xcom]
        out.append(batch[: n - got])
        got += len(out[-1])
        if got == n:
            return np.concatenate(out)
    raise RuntimeError(
        f'erroneous betas: only {got} of {n} drawn with |x_com| > {min_xcom} m; '
        'is the first pose degenerate?'
    )


def authors_betas(
    beta, n, rng, first_phi=None, min_xcom=None, max_deviation=None, max_offset=None
):
    """(n, len(beta)) erroneous betas by the authors' recipe around `beta` (the "real" one).

    first_phi: phi of the first pool pose (normalised by the nominal mass); min_xcom in m.
    """
    cfg = erroneous_config()
    dev = cfg['max_deviation'] if max_deviation is None else max_deviation
    off = cfg['max_offset_kgm'] if max_offset is None else max_offset
    min_xcom = cfg['min_xcom_m'] if min_xcom is None else min_xcom
    beta = np.asarray(beta, dtype=float)
    rng = np.random.default_rng(rng)
    moment = np.ones(beta.size, dtype=bool)
    moment[0::4] = False

    def draw(k):
        b = np.repeat(beta[None, :], k, axis=0)
        v = beta[moment]
        b[:, moment] = (
            v + rng.uniform(-dev, dev, (k, v.size)) * v + rng.uniform(-off, off, (k, v.size))
        )
        return b

    return _rejection_sample(draw, n, first_phi, min_xcom, rng)


def paper_betas(beta, n, rng, fraction=None, first_phi=None, min_xcom=0.0, quantities=(0, 1, 2)):
    """(n, len(beta)) betas with relative noise U(-f, f) on the quantities (0 = m, 1 = m*x, 2 =
    m*y,
    3 = m*z) of every body: the paper's "20 % from the real values of m_i, m_i x_i and m_i y_i"."""
    f = erroneous_config()['paper_fraction'] if fraction is None else fraction
    beta = np.asarray(beta, dtype=float)
    rng = np.random.default_rng(rng)
    sel = np.zeros(beta.size, dtype=bool)
    for k in quantities:
        sel[k::4] = True

    def draw(k):
        b = np.repeat(beta[None, :], k, axis=0)
        b[:, sel] *= 1.0 + rng.uniform(-f, f, (k, int(sel.sum())))
        return b

    return _rejection_sample(draw, n, first_phi, min_xcom, rng)
