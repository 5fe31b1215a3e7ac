"""The balance-point observer against a linear plant whose balance point it does not know (analytic
truth)."""

import math

import numpy as np
import pytest
from scipy.linalg import expm

from krang_adrc_controller.balance_point import BalancePointObserver, ObserverConfig

H = 0.002


def plant_step(a, b, delta):
    """Exact ZOH step of theta'' = a (theta - delta) + b tau over H, as a function of (state,
    tau)."""
    aug = np.zeros((4, 4))
    aug[0, 1] = 1.0
    aug[1, 0] = a
    aug[1, 2] = b
    aug[1, 3] = -a * delta
    e = expm(aug * H)

    def step(state, tau):
        return e[:2] @ np.array([state[0], state[1], tau, 1.0])

    return step


def model(a, b):
    """The observer's A, B rows: only the theta row (index 3) is read."""
    amat = np.zeros((4, 4))
    amat[3, 2] = a
    return amat, np.array([0.0, 0.0, 0.0, b])


@pytest.mark.parametrize('a, delta', [(-9.0, 0.1), (-9.0, -0.2), (25.0, 0.05)])
def test_estimates_the_balance_point_whatever_the_input(a, delta):
    """f = -a delta is the whole model error, so delta_hat -> delta under any input: here an
    open-loop sine on a stable plant (a < 0), and a stabilising PD on the unstable one (a > 0).
    While theta moves, the known part a theta is held over each period: f_hat is off by about a
    theta' H / 2, delta_hat by theta' H / 2 (bounded here by max |theta'| H)."""
    b = 2.0
    step = plant_step(a, b, delta)
    obs = BalancePointObserver(H, 20.0, ObserverConfig(time_constant_s=0.5))
    obs.set_model(*model(a, b))
    state = np.array([0.3, 0.0])
    obs.reset(state[0], state[1])
    rate = 0.0
    for k in range(int(10.0 / H)):
        obs.update(state[0], H)
        tau = math.sin(0.7 * k * H) if a < 0 else -(2.0 * a / b) * state[0] - (8.0 / b) * state[1]
        obs.applied(tau, state[0], 0.0, state[1])
        state = step(state, tau)
        rate = max(rate, abs(state[1])) if k * H > 8.0 else rate
    assert obs.delta == pytest.approx(delta, abs=max(rate * H, 1e-6))


def test_regulating_about_the_estimate_ends_at_the_true_balance_point():
    """A PD about theta - delta_hat (what BalanceController does) rests at theta = delta, with zero
    input."""
    a, b, delta = 20.0, 1.5, 0.12
    step = plant_step(a, b, delta)
    obs = BalancePointObserver(H, 20.0, ObserverConfig(time_constant_s=1.0))
    obs.set_model(*model(a, b))
    state = np.array([0.0, 0.0])
    obs.reset(0.0, 0.0)
    for _ in range(int(20.0 / H)):
        trim = obs.update(state[0], H)
        tau = -(3.0 * a / b) * (state[0] - trim) - (10.0 / b) * state[1]
        obs.applied(tau, state[0], 0.0, state[1])
        state = step(state, tau)
    assert state[0] == pytest.approx(delta, abs=1e-4)
    assert abs(tau) < 1e-3


def test_shift_hold_and_limit():
    a, b = 20.0, 1.5
    obs = BalancePointObserver(H, 20.0, ObserverConfig(time_constant_s=1.0, limit_rad=0.25))
    obs.set_model(*model(a, b))
    obs.reset(0.0, 0.0)
    obs.delta = 0.1
    obs.shift(0.03, same_pose=True)  # new beta, same pose: the true balance pitch stays
    assert obs.delta == pytest.approx(0.13)
    obs.shift(0.03, same_pose=False)  # new pose: the CoM-angle error is kept
    assert obs.delta == pytest.approx(0.13)
    # a plant 1 rad off the model: held, the estimate stays; free, it stops at the limit
    step, state = plant_step(-a, b, 1.0), np.array([0.0, 0.0])
    obs.reset(0.0, 0.0)
    obs.delta = 0.13
    for k in range(int(5.0 / H)):
        obs.update(state[0], H, hold=k < 1000)
        if k == 999:
            assert obs.delta == 0.13
        obs.applied(0.0, state[0], 0.0, state[1])
        state = step(state, 0.0)
    assert obs.delta == pytest.approx(0.25)
    with pytest.raises(ValueError):
        obs.set_model(*model(0.0, b))


def test_the_place_thresholds_must_be_positive():
    """balance_point.place_tol_m / place_speed_m_s: the flag while the joints move."""
    for bad in ({'place_tol_m': 0.0}, {'place_speed_m_s': -0.1}):
        with pytest.raises(ValueError):
            ObserverConfig(**bad)


def test_the_drive_observer_tells_a_drive_torque_from_a_com_error():
    """The x channel's observer separates a torque between wheels and body (the drive chain's
    friction or shortfall, loading x and theta as the motors do) from the CoM error (loading them
    as gravity does): on the WIP's linear model of the Table II pose, under LQR, with a CoM error
    of 20 mrad and a drive chain taking 6 N m, delta_hat -> 20 mrad and drive_hat -> -6 N m."""
    amat = np.array(
        [[0, 1, 0, 0], [0, -0.0135, -2.4846, 0.0036], [0, 0, 0, 1], [0, 0.0255, 12.629, -0.0068]]
    )
    bvec = np.array([0.0, 0.0359, 0.0, -0.0679])
    gain = np.array([-51.955, -116.558, -629.134, -197.345])  # tau = -gain . state
    delta, drive = 0.02, -6.0
    aug = np.zeros((6, 6))
    aug[:4, :4] = amat
    aug[:4, 4] = bvec
    aug[:4, 5] = bvec * drive - amat[:, 2] * delta
    e = expm(aug * H)
    obs = BalancePointObserver(H, 20.0, ObserverConfig(time_constant_s=0.5))
    obs.set_model(amat, bvec)
    state = np.array([0.0, 0.0, 0.05, 0.0])
    obs.reset(state[2], state[3], state[0], state[1])
    for _ in range(int(15.0 / H)):
        trim = obs.update(state[2], H, x=state[0])
        tau = -gain @ (state - np.array([0.0, 0.0, trim, 0.0]))
        obs.applied(tau, state[2], state[1], state[3])
        state = (e @ np.r_[state, tau, 1.0])[:4]
    assert obs.delta == pytest.approx(delta, abs=2e-4)
    assert obs.drive == pytest.approx(drive, abs=0.05)
    off = BalancePointObserver(H, 20.0, ObserverConfig(drive_observer=False))
    off.set_model(amat, bvec)
    assert off.drive == 0.0 and off.eso_x is None
