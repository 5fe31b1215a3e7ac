"""The operator's controls of the balance controller (core, offline closed loop): enable without
standing, stand_up, sit_down back onto the caster, halt, recover, a drive fault, and a refusal with
a reason wherever a control does not apply (README, "Running on the robot")."""

import numpy as np
import pytest

from krang_adrc_controller.modes import Mode
from krang_model.beta import load_beta
from krang_model.config import config_path
from krang_model.robot import load_krang
from krang_sim.closed_loop import ClosedLoop
from krang_sim.scenarios import TABLE2_POSE


@pytest.fixture(scope='module')
def robot():
    return load_krang()


@pytest.fixture(scope='module')
def true_beta(robot):
    return load_beta(config_path('sim_true_beta.yaml'), robot)


def refused(reply, *words):
    assert not reply.ok, reply.message
    assert reply.message.startswith('refused: ')
    for w in words:
        assert w in reply.message, reply.message


def test_full_operator_sequence(robot, true_beta):
    loop = ClosedLoop(robot, true_beta, true_beta, TABLE2_POSE, seed=5, log_rate_hz=0)
    ctl = loop.controller
    loop.run(0.2)
    assert ctl.mode is Mode.SAFE_STOP
    refused(ctl.request_stand(), 'safe_stop', 'recover')
    refused(ctl.request_sit(), 'safe_stop')
    assert ctl.request_enable(True).ok  # = recover: powered, sitting
    loop.run(5.0)
    assert ctl.mode is Mode.SIT, 'enable must not stand the robot up'
    assert max(abs(loop.last_output.current_left), abs(loop.last_output.current_right)) < 0.5
    refused(ctl.recover(), 'not in safe_stop')
    refused(ctl.request_sit(), 'already sitting')
    reply = ctl.request_stand()
    assert reply.ok and reply.message.startswith('started')
    refused(ctl.request_stand(), 'already requested')
    assert loop.run(12.0, until=lambda o: o.mode == 'balance')
    refused(ctl.request_stand(), 'already balancing')
    refused(ctl.request_enable(False), 'use sit_down or halt')
    assert ctl.mode is Mode.BALANCE
    assert ctl.request_sit().ok
    refused(ctl.request_sit(), 'already requested')
    loop.run(0.01)
    refused(ctl.request_sit(), 'already sitting down')
    refused(ctl.request_stand(), 'sitting down')
    assert loop.run(10.0, until=lambda o: o.mode == 'sit')
    loop.run(2.0)
    assert loop.sim.q_base < ctl.config.modes.sit_imu_limit_rad  # on the caster
    reply = ctl.request_enable(False)
    assert reply.ok and 'zero current' in reply.message
    loop.run(0.01)
    assert ctl.mode is Mode.SAFE_STOP and loop.last_output.current_left == 0.0
    assert ctl.request_stop('again').message.startswith('already in safe_stop')


def test_halt_zeroes_the_current_and_recover_sits_without_standing(robot, true_beta):
    loop = ClosedLoop(robot, true_beta, true_beta, TABLE2_POSE, seed=6, log_rate_hz=0)
    ctl = loop.controller
    loop.run(0.2)
    ctl.set_enabled(True)  # offline: stands at once
    assert loop.run(12.0, until=lambda o: o.mode == 'balance')
    assert ctl.request_stop('operator halt').ok
    loop.run(0.01)
    assert ctl.mode is Mode.SAFE_STOP
    assert loop.last_output.current_left == loop.last_output.current_right == 0.0
    assert any('stop reason: operator halt' in e for _, e in loop.events)
    loop.run(3.0)  # falls onto the caster
    assert ctl.recover().ok
    loop.run(4.0)
    assert ctl.mode is Mode.SIT  # no auto stand after a recover


def test_drive_fault_stops_and_blocks_recover_until_cleared(robot, true_beta):
    loop = ClosedLoop(robot, true_beta, true_beta, TABLE2_POSE, seed=7, log_rate_hz=0)
    ctl = loop.controller
    loop.run(0.2)
    ctl.set_enabled(True)
    assert loop.run(12.0, until=lambda o: o.mode == 'balance')
    ctl.set_drive_fault('JRWheel: FAULT statusword')
    loop.run(0.01)
    assert ctl.mode is Mode.SAFE_STOP and loop.last_output.current_right == 0.0
    assert any('drive fault: JRWheel' in e for _, e in loop.events)
    refused(ctl.recover(), 'drive fault (JRWheel', '/can_bridge/recover')
    refused(ctl.request_enable(True), '/can_bridge/recover')
    refused(ctl.request_stand(), 'drive fault')
    ctl.set_drive_fault('')
    loop.run(0.1)
    assert ctl.mode is Mode.SAFE_STOP  # a cleared fault does not restart
    assert ctl.recover().ok
    loop.run(0.5)
    assert ctl.mode is Mode.SIT


def test_stand_refused_outside_the_stand_window(robot, true_beta):
    """A model 20 cm off puts the CoM-angle error outside the window: the request is refused with
    the numbers, not accepted and then silently dropped."""
    wrong = true_beta.copy()
    wrong[2::4] += 0.2 * np.sign(wrong[2::4] + 1e-9)  # every body's CoM moved 20 cm
    loop = ClosedLoop(robot, true_beta, wrong, TABLE2_POSE, seed=8, log_rate_hz=0)
    ctl = loop.controller
    loop.run(0.2)
    assert ctl.recover().ok
    loop.run(0.5)
    window = ctl.modes.stand_refusal(loop.last_output.theta)
    assert window is not None, 'the test needs a theta outside the stand window'
    refused(ctl.request_stand(), 'CoM-angle error', 'outside')
    loop.run(1.0)
    assert ctl.mode is Mode.SIT
