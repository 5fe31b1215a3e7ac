"""ADRC law: hand-computed outputs, limits, the LQR switch, and closed loops on an analytic WIP
with a wrong CoM (measured theta = true theta + delta)."""

import numpy as np
import pytest
from scipy.linalg import expm

from krang_adrc_controller.adrc import AdrcConfig, AdrcController
from krang_adrc_controller.eso import EsoConfig
from krang_adrc_controller.lqr import LqrDesigner, channel_input_gains, split_gains
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang

from test_lqr import wip_ab

FX, FTH, BX, BTH = [-10.0, -20.0], [-500.0, -100.0], 0.4, -0.2
DRIVE = drivetrain(load_krang())
#: the authors' ESO gains (the shipped controller uses a bandwidth design)
AUTHORS_ESO = EsoConfig(omega_o=0.0)


def make(current_limit=100.0, **kw):
    drive = drivetrain(
        load_krang(), torque_constant=0.1, gear_ratio=10.0, current_limit=current_limit
    )
    return AdrcController(
        FX, FTH, BX, BTH, drive, sample_period_s=0.01, config=AdrcConfig(eso=AUTHORS_ESO, **kw)
    )


def test_first_step_by_hand():
    c = make()
    c.reset({'theta': 0.05, 'x': 0.2, 'dtheta': 0.0, 'dx': 0.0})
    cmd = c.update(0.05, 0.2, dtheta=0.0, dx=0.0)
    # consistent measurement -> no innovation -> f_hat = 0; tau = 10*0.2 + 500*0.05 = 27 N m
    assert cmd.fhat_x == 0.0 and cmd.fhat_theta == 0.0
    assert cmd.tau_total == pytest.approx(27.0)
    assert cmd.tau_left == pytest.approx(13.5) and cmd.tau_right == pytest.approx(13.5)
    assert cmd.i_left == pytest.approx(13.5 / (10.0 * 0.1)) and not cmd.saturated


def test_motor_constants_from_the_drive_train():
    c = AdrcController(FX, FTH, BX, BTH, DRIVE, sample_period_s=0.0333)
    c.reset((0.05, 0.2))
    cmd = c.update(0.05, 0.2, dtheta=0.0, dx=0.0)
    assert (DRIVE.gear_ratio, DRIVE.torque_constant) == (15.0, pytest.approx(0.0847, rel=1e-3))
    assert cmd.i_left == pytest.approx(13.5 / (DRIVE.gear_ratio * DRIVE.torque_constant))


def test_current_and_torque_limits_and_split():
    c = make(current_limit=5.0)
    c.reset((0.05, 0.2))
    cmd = c.update(0.05, 0.2, dtheta=0.0, dx=0.0)
    assert cmd.i_left == 5.0 and cmd.tau_left == pytest.approx(5.0) and cmd.saturated
    c = make(torque_limit_nm=3.0)
    c.reset((-0.05, -0.2))
    cmd = c.update(-0.05, -0.2, dtheta=0.0, dx=0.0)
    assert cmd.tau_right == pytest.approx(-3.0) and cmd.i_right == pytest.approx(-3.0)
    c = make(left_share=0.3)
    c.reset((0.05, 0.2))
    cmd = c.update(0.05, 0.2, dtheta=0.0, dx=0.0)
    assert (cmd.tau_left, cmd.tau_right) == (pytest.approx(0.3 * 27.0), pytest.approx(0.7 * 27.0))


def test_compensation_identity_and_lqr_switch():
    rng = np.random.default_rng(1)
    c = make()
    c.reset((0.0, 0.0))
    for k in range(50):
        th, x, dth, dx = rng.normal(0, 0.01, 4)
        cmd = c.update(th, x, dtheta=dth, dx=dx)
        u_x = -(FX[0] * x + FX[1] * dx)
        u_th = -(FTH[0] * th + FTH[1] * dth)
        assert (cmd.u_x, cmd.u_theta) == (pytest.approx(u_x), pytest.approx(u_th))
        if k < 25:
            assert cmd.tau_total == pytest.approx(
                u_x + u_th - cmd.fhat_x / BX - cmd.fhat_theta / BTH
            )
        else:
            assert cmd.tau_total == pytest.approx(u_x + u_th)  # plain LQR
            assert abs(cmd.fhat_x) + abs(cmd.fhat_theta) > 0  # observers still run
        if k == 24:
            c.set_disturbance_rejection(False)


# ---------------------------------------------------------------- closed loops with a wrong CoM

PLANT = dict(M=152.8, l=0.45, Ic=10.0, mw=9.32, Iw=0.27, r=0.25, b=0.2)
DELTA = 0.05  # CoM-angle error of the model (rad): theta_measured = theta_true + DELTA


def closed_loop(h, duration, *, adrc=True, eso_input='nominal', rates=True, **kw):
    A, B = wip_ab(**PLANT)
    K = LqrDesigner().gain(A, B)
    f_x, f_th = split_gains(K)
    b_x, b_th = channel_input_gains(B)
    drive = drivetrain(load_krang(), current_limit=1e6)
    c = AdrcController(
        f_x,
        f_th,
        b_x,
        b_th,
        drive,
        sample_period_s=h,
        config=AdrcConfig(
            use_disturbance_rejection=adrc, eso_input=eso_input, eso=AUTHORS_ESO, **kw
        ),
    )
    m = expm(np.block([[A, B[:, None]], [np.zeros((1, 5))]]) * h)
    ad, bd = m[:4, :4], m[:4, 4]
    X = np.array([0.0, 0.0, 0.1, 0.0])  # start 0.1 rad off balance
    log = []
    for k in range(int(round(duration / h))):
        cmd = c.update(
            X[2] + DELTA, X[0], dtheta=X[3] if rates else None, dx=X[1] if rates else None
        )
        X = ad @ X + bd * cmd.tau_total
        log.append(
            [(k + 1) * h, *X, cmd.tau_total, cmd.fhat_x, cmd.fhat_theta, cmd.u_x, cmd.u_theta]
        )
    return np.array(log), f_x, f_th, b_x, b_th


@pytest.mark.parametrize('h', [1 / 30, 0.002])
@pytest.mark.parametrize('adrc', [True, False], ids=['adrc', 'lqr'])
@pytest.mark.parametrize('rates', [True, False], ids=['measured_rates', 'eso_rates'])
def test_wrong_com_settles_at_the_lqr_equilibrium(h, adrc, rates):
    """At rest tau = 0 and the true CoM is over the axle (theta_true = 0, measured = DELTA). With
    the authors' ESO input the rest point is the LQR one: F_x0 x + F_th0 DELTA = 0, i.e. the
    'resting position' offset x = -F_th0 DELTA / F_x0 of Table II."""
    log, f_x, f_th, b_x, b_th = closed_loop(h, 60.0, adrc=adrc, rates=rates)
    x, dx, th, dth, tau = log[-1, 1:6]
    assert abs(th) < 1e-6 and abs(dx) < 1e-6 and abs(dth) < 1e-6 and abs(tau) < 1e-4
    assert x == pytest.approx(-f_th[0] * DELTA / f_x[0], rel=1e-4)
    assert np.max(np.abs(log[:, 3])) < 0.2  # never near falling
    # each ESO sits where its model predicts no acceleration: f_hat = -b * u_nominal
    fhat_x, fhat_th, u_x, u_th = log[-1, 6:10]
    assert fhat_x == pytest.approx(-b_x * u_x, rel=1e-3)
    assert fhat_th == pytest.approx(-b_th * u_th, rel=1e-3)


def test_applied_input_variant_winds_up():
    """Textbook ESO inputs demand x = 0 and theta_measured = 0 at rest, impossible with DELTA != 0:
    the estimates grow without bound in opposite directions while the torque stays ~0."""
    log, _, _, b_x, b_th = closed_loop(1 / 30, 60.0, eso_input='applied')
    nominal, *_ = closed_loop(1 / 30, 60.0)
    i30 = int(round(30 * 30)) - 1
    assert abs(log[-1, 6]) > 1.8 * abs(log[i30, 6])  # ~linear growth
    assert abs(log[-1, 6]) > 100 * abs(nominal[-1, 6])
    comp_x, comp_th = log[-1, 6] / b_x, log[-1, 7] / b_th
    assert abs(comp_x + comp_th) < 1e-2 * abs(comp_x)  # they cancel each other
    assert abs(log[-1, 5]) < 1e-3
