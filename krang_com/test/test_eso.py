"""Discrete ESO: pole locations (hand/closed form, Ackermann, python-control), Euler's failure,
and convergence on a double integrator at several sample rates."""

import control as ct
import numpy as np
import pytest

from krang_adrc_controller.eso import (
    AUTHORS_CONTINUOUS_GAINS,
    ExtendedStateObserver,
    bandwidth_gains,
    chain_model,
    continuous_poles,
    current_gains_for_poles,
    euler_transition_matrix,
    matched_gains,
    spectral_radius,
)

RATES = [0.002, 0.003, 0.010, 0.033]


def test_authors_gain_poles():
    """The authors' gains (munzir/18d): L = (1160, 173438.396, 1343839.408) -> poles -985.4,
    -166.4, -8.19 rad/s."""
    p = np.sort(continuous_poles(AUTHORS_CONTINUOUS_GAINS).real)
    assert p == pytest.approx([-985.4, -166.4, -8.19], abs=0.05)


@pytest.mark.parametrize('h', RATES)
def test_bandwidth_design_puts_all_poles_at_exp_minus_wh(h):
    w = 25.0
    eso = ExtendedStateObserver(1.7, h, omega_o=w)
    beta = np.exp(-w * h)
    # characteristic polynomial (z - beta)^3, robust to the numerical split of a triple root
    assert np.poly(eso.transition_matrix()) == pytest.approx(np.poly([beta] * 3), abs=1e-9)
    assert np.abs(np.linalg.eigvals(eso.transition_matrix())) == pytest.approx(
        [beta] * 3, abs=1e-4
    )


@pytest.mark.parametrize('h', RATES)
def test_closed_form_equals_ackermann_and_python_control(h):
    w = 40.0
    beta = np.exp(-w * h)
    closed = bandwidth_gains(w, h)
    assert current_gains_for_poles([beta] * 3, h) == pytest.approx(closed, rel=1e-8)
    # python-control as a third implementation, on the matched authors' poles (distinct)
    ad, _ = chain_model(h, 1.0)
    c = np.array([[1.0, 0.0, 0.0]])
    z = np.exp(continuous_poles(AUTHORS_CONTINUOUS_GAINS) * h)
    ref = np.asarray(ct.acker(ad.T, (c @ ad).T, z)).ravel()
    assert matched_gains(AUTHORS_CONTINUOUS_GAINS, h) == pytest.approx(ref, rel=1e-7, abs=1e-9)


def test_authors_euler_is_unstable_at_3ms_ours_is_not():
    """Euler's eigenvalues are 1 + h p_i (hand): at 3 ms, 1 - 0.003 * 985.37 = -1.956."""
    p = continuous_poles(AUTHORS_CONTINUOUS_GAINS)
    eul = euler_transition_matrix(AUTHORS_CONTINUOUS_GAINS, 0.003)
    assert np.sort(np.linalg.eigvals(eul).real) == pytest.approx(
        np.sort(1 + 0.003 * p.real), abs=1e-6
    )
    assert spectral_radius(eul) == pytest.approx(1.956, abs=2e-3)
    assert spectral_radius(euler_transition_matrix(AUTHORS_CONTINUOUS_GAINS, 0.002)) < 1.0
    for h in RATES:
        for method in ('current', 'zoh'):
            eso = ExtendedStateObserver(1.0, h, method=method)
            assert spectral_radius(eso.transition_matrix()) < 1.0
            # matched: eigenvalues exp(p_i h) exactly
            assert np.sort(np.abs(np.linalg.eigvals(eso.transition_matrix()))) == pytest.approx(
                np.sort(np.exp(p.real * h)), abs=1e-9
            )
        if h >= 0.003:
            assert spectral_radius(euler_transition_matrix(AUTHORS_CONTINUOUS_GAINS, h)) > 1.0


def test_stable_at_any_sample_period():
    for h in np.logspace(-4, 0.5, 25):
        for kw in ({'omega_o': 5.0}, {'omega_o': 300.0}, {}):
            for method in ('current', 'zoh'):
                eso = ExtendedStateObserver(3.0, h, method=method, **kw)
                assert spectral_radius(eso.transition_matrix()) < 1.0


def simulate(eso, h, duration, f_fun, b=2.0, jitter=None, seed=0):
    """Exact-ish double integrator y'' = f(t) + b u (u held, 20 substeps), PD + sine input; the
    ESO gets y and the held u. Returns rows (t, f_hat, f_true)."""
    rng = np.random.default_rng(seed)
    y, v, t, u = 0.3, 0.0, 0.0, 0.0
    eso.reset(y)
    out = []
    while t < duration:
        hk = h if jitter is None else h * (1 + jitter * (2 * rng.random() - 1))
        sub = hk / 20
        for _ in range(20):
            a = f_fun(t + 0.5 * sub) + b * u
            y += v * sub + 0.5 * a * sub * sub
            v += a * sub
            t += sub
        z = eso.update(y, u, None if jitter is None else hk)
        u = (-4.0 * (y - 1.0) - 4.0 * z[1] - z[2]) / b + 0.5 * np.sin(1.3 * t)
        out.append((t, z[2], f_fun(t)))
    return np.array(out)


@pytest.mark.parametrize('h', RATES)
@pytest.mark.parametrize('design', [{'omega_o': 10.0}, {}], ids=['bandwidth10', 'authors'])
def test_converges_to_constant_disturbance(h, design):
    """With f constant the sampled model is exact, so the current ESO's error decays to ~0."""
    out = simulate(ExtendedStateObserver(2.0, h, **design), h, 6.0, lambda t: 3.0)
    assert abs(out[-1, 1] - 3.0) < 1e-6
    assert abs(out[0, 1] - 3.0) > 0.1  # it really had to converge


def test_converges_with_jittery_period():
    out = simulate(
        ExtendedStateObserver(2.0, 0.033, omega_o=10.0), 0.033, 6.0, lambda t: -1.5, jitter=0.3
    )
    assert abs(out[-1, 1] + 1.5) < 1e-6


@pytest.mark.parametrize('h', RATES)
@pytest.mark.parametrize(
    'design,lag',
    [
        ({'omega_o': 10.0}, 3 / 10.0),
        ({}, AUTHORS_CONTINUOUS_GAINS[1] / AUTHORS_CONTINUOUS_GAINS[2]),
    ],
    ids=['bandwidth10', 'authors'],
)
def test_tracks_slow_disturbance_with_analytic_lag(h, design, lag):
    """f = 1 + A sin(w t), w slow: f_hat = l3/(s^3+l1 s^2+l2 s+l3) f, so the tracking error
    amplitude is ~ A w l2/l3 (3 A w / w_o for the bandwidth design)."""
    amp, w = 0.5, 0.3
    out = simulate(
        ExtendedStateObserver(2.0, h, **design), h, 40.0, lambda t: 1.0 + amp * np.sin(w * t)
    )
    late = out[:, 0] > 10.0
    err = np.max(np.abs(out[late, 1] - out[late, 2]))
    assert err == pytest.approx(amp * w * lag, rel=0.15)


def test_initialised_from_measurement_and_saturation():
    eso = ExtendedStateObserver(1.0, 0.01, omega_o=20.0, f_limit=2.0)
    z = eso.update(0.7, 0.0)  # first call initialises: no peaking
    assert z == pytest.approx([0.7, 0.0, 0.0])
    z = eso.update(0.7, 0.0)  # consistent measurement: nothing moves
    assert z == pytest.approx([0.7, 0.0, 0.0])
    out = simulate(eso, 0.01, 3.0, lambda t: 10.0)
    assert np.max(np.abs(out[:, 1])) <= 2.0 + 1e-12
