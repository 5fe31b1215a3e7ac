"""Mode machine, transition by transition, with the 2018 hardware's guards (docs/control.md)."""

import math
from dataclasses import replace

import pytest

from krang_adrc_controller.modes import (
    GROUND_LO_GAINS,
    SIT_GAINS,
    STAND_GAINS,
    Mode,
    ModeInputs,
    ModeMachine,
    ModesConfig,
    SafetyConfig,
    pd_currents,
)
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang

DEG = math.pi / 180
H = 0.0333
#: the 2018 hardware's guards, where the shipped configuration differs (its docs say why)
HARDWARE = ModesConfig(
    stand_error_min_rad=-10.0 * DEG,
    balance_imu_min_rad=-101.0 * DEG,
    sit_waist_min_rad=150.0 * DEG,
    sit_imu_limit_rad=-103.0 * DEG,
)


def machine(safety=SafetyConfig(), **kw):
    return ModeMachine(replace(HARDWARE, **kw), safety)


def inp(t, **kw):
    base = dict(
        imu_pitch=-101.5 * DEG, theta_com=-5 * DEG, dtheta=0.0, waist=160 * DEG, last_sensor_t=t
    )
    base.update(kw)
    return ModeInputs(t=t, **base)


def standing(m, t0=0.0):
    out = m.step(inp(t0, stand_request=True))
    assert out.mode is Mode.STAND_UP
    return out


def test_starts_sitting_with_ground_gains():
    out = machine().step(inp(0.0))
    assert out.mode is Mode.SIT and out.controller == 'ground_pd'
    assert out.gains == GROUND_LO_GAINS and not out.zero_torque and not out.entered


@pytest.mark.parametrize(
    'theta_deg,ok',
    [(-12, False), (-10.01, False), (-10, True), (-5, True), (0, True), (0.5, False)],
)
def test_stand_guard_com_angle_error_in_minus10_to_0_deg(theta_deg, ok):
    m = machine()
    out = m.step(inp(0.0, theta_com=theta_deg * DEG, stand_request=True))
    assert (out.mode is Mode.STAND_UP) == ok
    assert out.entered == ok
    if ok:
        assert out.controller == 'stand_pd' and out.gains == STAND_GAINS
    else:
        assert out.mode is Mode.SIT and any('stand_refused' in e for e in out.events)


def test_stand_to_balance_after_continuous_settle_time():
    m = machine()
    standing(m)
    t = 0.0
    # still on the caster: IMU at -101.5 deg < -101 deg, never switches
    for _ in range(200):
        t += H
        assert m.step(inp(t, dtheta=0.0)).mode is Mode.STAND_UP
    # lifted, but moving too fast
    for _ in range(100):
        t += H
        assert m.step(inp(t, imu_pitch=-95 * DEG, dtheta=0.05)).mode is Mode.STAND_UP
    # quiet from t_q on: needs stand_settle_s (1 s) continuously
    t += H
    t_q = t
    m.step(inp(t, imu_pitch=-95 * DEG, dtheta=0.01))
    while t + H < t_q + 1.0 - 1e-9:
        t += H
        assert m.step(inp(t, imu_pitch=-95 * DEG, dtheta=-0.02)).mode is Mode.STAND_UP
    t += H
    out = m.step(inp(t, imu_pitch=-95 * DEG, dtheta=0.0))
    assert out.mode is Mode.BALANCE and out.entered and out.controller == 'adrc'
    assert out.gains is None and not out.zero_torque


def test_settle_timer_restarts_when_interrupted():
    m = machine(stand_settle_s=1.0)
    standing(m)
    m.step(inp(0.1, imu_pitch=-95 * DEG))
    m.step(inp(0.9, imu_pitch=-95 * DEG))
    m.step(inp(1.0, imu_pitch=-95 * DEG, dtheta=0.04))  # breaks the run
    assert m.step(inp(1.5, imu_pitch=-95 * DEG)).mode is Mode.STAND_UP
    assert m.step(inp(2.4, imu_pitch=-95 * DEG)).mode is Mode.STAND_UP
    assert m.step(inp(2.5, imu_pitch=-95 * DEG)).mode is Mode.BALANCE


def balancing(m):
    standing(m)
    assert m.step(inp(0.1, imu_pitch=-90 * DEG)).mode is Mode.BALANCE
    return m


def test_sit_down_guard_and_completion():
    m = machine(stand_settle_s=0.0)
    balancing(m)
    out = m.step(inp(1.0, imu_pitch=-90 * DEG, waist=140 * DEG, sit_request=True))
    assert out.mode is Mode.BALANCE and any('sit_refused' in e for e in out.events)
    out = m.step(inp(1.1, imu_pitch=-90 * DEG, waist=None, sit_request=True))
    assert out.mode is Mode.BALANCE
    out = m.step(inp(1.2, imu_pitch=-90 * DEG, waist=151 * DEG, sit_request=True))
    assert out.mode is Mode.SIT_DOWN and out.entered and out.gains == SIT_GAINS
    assert m.step(inp(1.3, imu_pitch=-102.9 * DEG)).mode is Mode.SIT_DOWN
    out = m.step(inp(1.4, imu_pitch=-103.1 * DEG))
    assert out.mode is Mode.SIT and out.entered and out.controller == 'ground_pd'


def test_refusals_say_why_with_the_numbers():
    """The reasons the operator's stand_up and sit_down see (the same checks as the step)."""
    m = machine()
    assert m.stand_refusal(-5 * DEG) is None
    why = m.stand_refusal(-12 * DEG)
    assert 'CoM-angle error -0.2094 rad outside [-0.1745, 0.0000] rad' == why
    assert m.sit_refusal(151 * DEG) is None
    assert m.sit_refusal(140 * DEG) == 'waist 2.443 rad not above the sit threshold 2.618 rad'
    assert 'unknown' in m.sit_refusal(None)
    out = m.step(inp(0.0, theta_com=-12 * DEG, stand_request=True))
    assert out.events == ['stand_refused: ' + why]


@pytest.mark.parametrize('start', ['sit', 'stand', 'balance', 'sit_down'])
def test_stop_request_latches_safe_stop_from_every_mode(start):
    m = machine(stand_settle_s=0.0)
    if start != 'sit':
        standing(m)
    if start in ('balance', 'sit_down'):
        m.step(inp(0.1, imu_pitch=-90 * DEG))
    if start == 'sit_down':
        m.step(inp(0.2, imu_pitch=-90 * DEG, sit_request=True))
    out = m.step(inp(0.5, stop_request=True))
    assert out.mode is Mode.SAFE_STOP and out.zero_torque and out.controller == 'off'
    # latched: requests and fresh data do not leave it
    for t in (0.6, 0.7):
        out = m.step(inp(t, stand_request=True))
        assert out.mode is Mode.SAFE_STOP and out.zero_torque
    out = m.step(inp(0.8, reset_request=True, stop_request=True))
    assert out.mode is Mode.SAFE_STOP
    out = m.step(inp(0.9, reset_request=True))
    assert out.mode is Mode.SIT and out.entered and not out.zero_torque


def test_stale_sensors_stop_and_block_reset():
    m = machine(SafetyConfig(stale_timeout_s=0.1), stand_settle_s=0.0)
    balancing(m)
    assert m.step(inp(1.00, last_sensor_t=0.95, imu_pitch=-90 * DEG)).mode is Mode.BALANCE
    out = m.step(inp(1.06, last_sensor_t=0.95, imu_pitch=-90 * DEG))  # 0.11 s old
    assert out.mode is Mode.SAFE_STOP and out.zero_torque
    out = m.step(inp(1.2, last_sensor_t=0.95, reset_request=True))
    assert out.mode is Mode.SAFE_STOP and any('reset_refused' in e for e in out.events)
    assert m.step(inp(1.3, reset_request=True)).mode is Mode.SIT


def test_fall_guard():
    m = machine(SafetyConfig(fall_angle_rad=0.5), stand_settle_s=0.0)
    balancing(m)
    assert m.step(inp(1.0, imu_pitch=-90 * DEG, theta_com=0.49)).mode is Mode.BALANCE
    assert m.step(inp(1.1, imu_pitch=-90 * DEG, theta_com=-0.51)).mode is Mode.SAFE_STOP
    # on by default, at 0.6 rad; 0 turns it off (the 2018 code had none)
    m = machine(stand_settle_s=0.0)
    balancing(m)
    assert m.step(inp(1.0, imu_pitch=-90 * DEG, theta_com=0.59)).mode is Mode.BALANCE
    assert m.step(inp(1.1, imu_pitch=-90 * DEG, theta_com=0.61)).mode is Mode.SAFE_STOP
    m = machine(SafetyConfig(fall_angle_rad=0.0), stand_settle_s=0.0)
    balancing(m)
    assert m.step(inp(1.0, imu_pitch=-90 * DEG, theta_com=1.0)).mode is Mode.BALANCE


def test_pd_currents_by_hand():
    lim = dict(
        spin_limit_a=ModesConfig().spin_limit_a,
        current_limit_a=drivetrain(load_krang()).current_limit,
    )
    assert lim == {'spin_limit_a': 30.0, 'current_limit_a': 49.0}
    e = (0.02, -0.1, 0.5, 0.2, 0.0, 0.0)
    u = 277.4 * 0.02 + 61.889 * -0.1 + 7.4484 * 0.5 + 18.235 * 0.2
    left, right = pd_currents(STAND_GAINS, e, **lim)
    assert left == pytest.approx(u) and right == pytest.approx(u)
    # spin term: u_spin = -(K_psi e_psi + K_dpsi e_dpsi), clamped to +/-30 A, added left / right
    left, right = pd_currents(GROUND_LO_GAINS, (0, 0, 0, 0.0, 0.0, 1.0), **lim)
    assert (left, right) == (pytest.approx(15.0), pytest.approx(-15.0))
    left, right = pd_currents(GROUND_LO_GAINS, (0, 0, 0, 0.0, 0.0, 3.0), **lim)
    assert (left, right) == (30.0, -30.0)
    left, right = pd_currents(STAND_GAINS, (1.0, 0, 0, 0, 0, 0), **lim)
    assert (left, right) == (49.0, 49.0)


def test_a_stand_up_back_on_its_caster_sits_with_a_reason():
    m = machine()
    standing(m)
    out = m.step(inp(0.1, imu_pitch=-101.5 * DEG, on_caster=True))
    assert out.mode is Mode.SIT and out.entered and out.controller == 'ground_pd'
    assert 'caster' in out.events[0]


def test_the_stand_up_catch_arms_at_lift_off_and_retries_a_bounded_number_of_times():
    from krang_adrc_controller.stand import StandUp

    caster = drivetrain(load_krang()).caster_pitch
    modes, safety = ModesConfig(stand_tries=2), SafetyConfig()
    stand = StandUp(modes, safety, caster, 0.002)
    stand.enter()
    # sitting on the caster before lift-off is no fall-back
    assert not any(stand.caught(0.01 * k, caster) for k in range(100))
    assert stand.lifts_off(1.0, caster + 2 * modes.stand_liftoff_rad)
    for k in range(100):  # the observer's estimate while lifted
        stand.watch(1.0 + 0.01 * k, -0.06)
    assert stand.reference(caster + 0.1, 0.0) == 0.0  # a first try: the model's balance
    caught = [stand.caught(2.0 + 0.01 * k, caster) for k in range(30)]
    assert sum(caught) == 1 and not stand.exhausted
    assert stand.trim == pytest.approx(-0.06)
    # the next try waits for rest, then regulates about the estimate once lifted
    assert not stand.ready(3.0, 0.3, 0.0)
    assert not stand.ready(3.1, 0.0, 0.0)
    assert stand.ready(3.11 + modes.stand_retry_rest_s, 0.0, 0.0)
    stand.enter()
    offset = 1.66  # theta - q_base: the model's CoM offset; on the caster theta = -0.1028
    assert stand.reference(caster, caster + offset) == 0.0  # before lift-off: the full error
    stand.lifts_off(5.0, caster + 0.1)
    # blended in as the body rises to the estimated balance pitch, then the whole estimate
    assert stand.reference(caster + 0.02, caster + 0.02 + offset) == pytest.approx(
        -0.06 * 0.02 / (-0.06 - caster - offset)
    )
    assert stand.reference(caster + 0.1, caster + 0.1 + offset) == pytest.approx(-0.06)
    stand.last_current = 20.0  # pressing the body onto its caster when it is caught
    assert sum(stand.caught(6.0 + 0.01 * k, caster) for k in range(30)) == 1
    assert stand.exhausted  # the controller then stays in SIT until the operator's stand_up
    stand.grant()
    assert not stand.exhausted and stand.trim == pytest.approx(-0.06)
    # a stand-up that reaches BALANCE hands its own estimate over, a retry and a first try
    # alike, and the tries are granted again
    stand.enter()
    stand.lifts_off(9.0, caster + 0.1)
    for k in range(100):
        stand.watch(9.0 + 0.01 * k, -0.05)
    assert stand.balanced() == pytest.approx(-0.05) and stand.tries == 0 and stand.trim == 0.0
    stand.enter()
    stand.lifts_off(11.0, caster + 0.1)
    for k in range(100):
        stand.watch(11.0 + 0.01 * k, -0.04)
    assert stand.balanced() == pytest.approx(-0.04)
    stand.enter()  # an observer that did not watch (no lift-off seen) hands over nothing
    assert stand.balanced() == 0.0
    # after a catch: while rolling forward a pitch PI, from the current at the catch, holds
    # the body just above its caster; once stopped the brake is limited
    gains = STAND_GAINS
    stand.tries, stand.last_current = 0, 20.0
    stand.enter()
    stand.lifts_off(7.0, caster + 0.1)
    assert sum(stand.caught(8.0 + 0.01 * k, caster) for k in range(30)) == 1
    u_th, u_x = stand.after_catch(0.0, -30.0, stand.hover_pitch, 0.0, 0.5, gains)
    assert u_x == 0.0 and u_th == pytest.approx(20.0)
    u_th, _ = stand.after_catch(0.0, -30.0, stand.hover_pitch + 0.01, 0.0, 0.5, gains)
    assert u_th > 20.0 + gains[0] * 0.01  # lifting: pushed back, and the integral grows
    u_th, u_x = stand.after_catch(0.0, -30.0, caster, 0.0, 0.0, gains)
    assert (u_th, u_x) == (0.0, -modes.stand_catch_brake_a)
