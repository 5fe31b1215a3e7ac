"""LQR(q): stability on analytic WIP models, agreement with scipy's CARE, the authors' Q mapping,
unit handling, and the pose/beta gain cache."""

import numpy as np
import pytest
from scipy.linalg import solve_continuous_are

from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang
from krang_model.wip import linearize, reduce_pose
from krang_adrc_controller.lqr import (
    AUTHORS_Q_DIAG,
    AUTHORS_R,
    GainCache,
    LqrDesigner,
    channel_input_gains,
    lqr_gain,
    split_gains,
)

G = 9.81


def wip_ab(M, l, Ic, mw, Iw, r, b=0.0, bg=0.0):  # noqa: E741 - l is the paper's CoM distance
    """Linearised WIP of notes/identification.md §6, state [phi, phi', theta, theta'] (phi = wheel
    angle in rad, the authors' x), input = total wheel torque."""
    a = (M + mw) * r**2 + Iw
    jc = Ic + M * l**2
    mrl = M * r * l
    d = jc * a - mrl**2
    c1, c2 = a + mrl, jc + mrl
    A = np.zeros((4, 4))
    A[0, 1] = A[2, 3] = 1.0
    A[1] = [0.0, -(b * c2 + bg * jc) / d, -(M**2) * G * l**2 * r / d, b * c2 / d]
    A[3] = [0.0, (b * c1 + bg * mrl) / d, M * G * l * a / d, -b * c1 / d]
    B = np.array([0.0, c2 / d, 0.0, -c1 / d])
    return A, B


# a few locked poses of a Krang-sized robot plus the notes' small example
MODELS = [
    dict(M=30.0, l=0.5, Ic=3.0, mw=2.0, Iw=0.02, r=0.25),
    dict(M=152.8, l=0.45, Ic=10.0, mw=9.32, Iw=0.27, r=0.25, b=0.2),
    dict(M=152.8, l=0.60, Ic=25.0, mw=9.32, Iw=0.27, r=0.2667, b=0.1, bg=0.5),
    dict(M=152.8, l=0.25, Ic=6.0, mw=9.32, Iw=0.27, r=0.2667),
]


@pytest.mark.parametrize('p', MODELS)
def test_test_model_unstable_pole_matches_cart_pendulum_formula(p):
    """Frictionless: theta'' = M g l (M + m_c) / ((M + m_c)(Ic + M l^2) - M^2 l^2) theta with the
    wheels as a cart of mass m_c = m_w + I_w / r^2 (independent derivation)."""
    q = dict(p, b=0.0, bg=0.0)
    A, _ = wip_ab(**q)
    mc = q['mw'] + q['Iw'] / q['r'] ** 2
    M, l, Ic = q['M'], q['l'], q['Ic']  # noqa: E741
    pole = np.sqrt(M * G * l * (M + mc) / ((M + mc) * (Ic + M * l * l) - (M * l) ** 2))
    assert np.max(np.linalg.eigvals(A).real) == pytest.approx(pole, rel=1e-9)


@pytest.mark.parametrize('p', MODELS)
def test_closed_loop_stable_and_equal_to_care(p):
    A, B = wip_ab(**p)
    designer = LqrDesigner()
    K = designer.gain(A, B)
    assert np.all(np.linalg.eigvals(A - np.outer(B, K)).real < 0)
    # second implementation: K = R^-1 B^T P, P from scipy's continuous ARE
    P = solve_continuous_are(A, B.reshape(4, 1), designer.q, np.array([[designer.r]]))
    assert K == pytest.approx((B @ P) / designer.r, rel=1e-7)


def test_authors_q_order_reproduces_hardware_x_gain():
    """Kalman's equality at w -> 0 gives |K_x| = sqrt(Q_x / R) when x is a free integrator.
    With the weights mapped to our order the x gain is sqrt(96000/500) = 13.8564, the hardware's
    value; reading the kit summary's order literally would give sqrt(30000/500) = 7.746."""
    A, B = wip_ab(**MODELS[1])
    K = LqrDesigner().gain(A, B)
    assert abs(K[0]) == pytest.approx(13.8564, abs=1e-4)
    assert AUTHORS_Q_DIAG == (96000.0, 90000.0, 300.0, 30000.0) and AUTHORS_R == 500.0
    literal = np.diag([30000.0, 90000.0, 300.0, 96000.0])  # (th, dth, x, dx) read as written
    assert abs(lqr_gain(A, B, literal, 500.0)[0]) == pytest.approx(np.sqrt(30000 / 500), abs=1e-4)


def test_metres_model_gives_the_same_controller():
    """x_m = r x_rad: A_m = T A T^-1, B_m = T B, and the same weights per wheel radian must give
    K_m = K_rad T^-1."""
    r = 0.2667
    A, B = wip_ab(**MODELS[2])
    T = np.diag([r, r, 1.0, 1.0])
    Ti = np.linalg.inv(T)
    K_rad = LqrDesigner().gain(A, B)
    K_m = LqrDesigner(position_unit='m', wheel_radius_m=r).gain(T @ A @ Ti, T @ B)
    assert K_m == pytest.approx(K_rad @ Ti, rel=1e-7)
    with pytest.raises(ValueError):
        LqrDesigner(position_unit='m')


def test_split_and_channel_gains():
    f_x, f_th = split_gains([1.0, 2.0, 3.0, 4.0])
    assert f_x.tolist() == [1.0, 2.0] and f_th.tolist() == [3.0, 4.0]
    assert channel_input_gains(np.array([[0.0], [0.5], [0.0], [-0.2]])) == (0.5, -0.2)


def test_gain_cache_recomputes_only_on_change():
    calls = []

    def linearize(pose, beta):
        calls.append(1)
        l = 0.3 + 0.1 * float(pose[0])  # noqa: E741 + 0.01 * float(np.sum(beta))
        return wip_ab(M=152.8, l=l, Ic=10.0, mw=9.32, Iw=0.27, r=0.25)

    cache = GainCache(linearize, pose_decimals=3, beta_decimals=6, maxsize=2)
    beta = np.array([1.0, 2.0])
    d1 = cache.design([0.5, 1.0], beta)
    assert cache.design([0.5 + 2e-4, 1.0 - 3e-4], beta + 1e-8) is d1  # same rounded key
    assert len(calls) == 1
    d2 = cache.design([0.6, 1.0], beta)  # pose changed
    assert len(calls) == 2 and d2 is not d1
    cache.design([0.6, 1.0], beta + 1e-3)  # beta changed
    assert len(calls) == 3 and cache.recomputations == 3
    assert cache.design([0.6, 1.0], beta + 1e-3) is not None and len(calls) == 3
    cache.design([0.5, 1.0], beta)  # evicted (maxsize 2)
    assert len(calls) == 4
    A, B = linearize([0.6], beta)
    assert d2['F_x'].tolist() + d2['F_theta'].tolist() == pytest.approx(
        LqrDesigner().gain(*linearize([0.6, 1.0], beta)).tolist()
    )
    assert (d2['b_x'], d2['b_theta']) == (pytest.approx(B[1]), pytest.approx(B[3]))


def test_with_project_wip_model():
    """krang_model.wip.linearize (x in metres) at the zero pose: stable design, and the
    metres/radians bookkeeping gives |K_x| = 13.8564 / r."""
    robot = load_krang()
    body = reduce_pose(robot, np.zeros(16), robot.nominal_beta)
    A, B = linearize(body, drivetrain(robot))
    r = robot.wheel_radius
    K = LqrDesigner(position_unit='m', wheel_radius_m=r).gain(A, B)
    assert np.all(np.linalg.eigvals(A - np.outer(np.ravel(B), K)).real < 0)
    assert abs(K[0]) == pytest.approx(np.sqrt(96000 / 500) / r, rel=1e-4)
