"""The arm fault without DDS: a PowerCube module that answered and then falls silent latches a
fault naming it and its joint (BridgeCore), the wheels keep their current, its joint stays in the
joint state at its last position with velocity 0, commands to it produce no frames while the
other joints move, and only a recover with every module answering clears it (BridgeRuntime,
which reports the fault once per change and resends the module's start-up)."""

import struct

from krang_can_bridge.snapshots import ERROR, OK
from krang_model.robot import load_krang
from test_can_bridge_core import CFG, check_joint_frames_within_limits, healthy_core, msg
from test_can_bridge_core import wheel_amps_by_hand
from test_can_bridge_runtime import Rig

SILENT = CFG.powercube.joint('LJ2').modules[0]
KEY = (SILENT.bus, SILENT.module_id)


def feed_all_but(dev, t, silent=(KEY,)):
    """Every device's frames at `t`, but no replies from the modules in `silent`."""
    dev.feed(t, modules=False)
    for (bus, mid), pos in dev.module_pos.items():
        if (bus, mid) in silent:
            continue
        dev.core.on_frame(msg(0x0A0 + mid, bytes([0x0A, 0x3C]) + struct.pack('<f', pos)), t, bus)
        dev.core.on_frame(msg(0x0A0 + mid, bytes([0x0A, 0x41]) + struct.pack('<f', 0.1)), t, bus)


def go_silent(core, dev, t, silent=(KEY,)):
    """Run the devices, those in `silent` quiet, for the modules' silence timeout and more."""
    end = t + CFG.powercube.silence_timeout_s + 0.05
    while t < end:
        t += 0.002
        feed_all_but(dev, t, silent)
    return t


def test_a_silent_module_latches_an_arm_fault_and_the_wheels_keep_their_current():
    core, dev, t = healthy_core()
    dev.module_pos[KEY] = 0.25
    dev.feed(t + 0.001)
    t += 0.001
    assert core.arm_fault(t) == ('', [])
    t = go_silent(core, dev, t)
    reason, joints = core.arm_fault(t)
    assert joints == ['LJ2'] and 'LJ2' in reason and 'not answering' in reason, reason
    # the wheels: driven as before (a balancing robot would fall back onto its caster)
    assert core.motion_allowed(t)
    assert abs(wheel_amps_by_hand(core.wheel_current_frames(20.0, 20.0, t)[0])) > 10
    # the silent joint: held at its last position, velocity 0, the others measured
    state = core.joint_state(t)
    i = state.names.index('LJ2')
    assert state.positions[i] == 0.25 * SILENT.sign and state.velocities[i] == 0.0
    assert state.velocities[state.names.index('LJ1')] != 0.0
    assert set(load_krang().pose_joints) <= set(state.names)
    # commands: none to the silent module, the others go out
    frames = core.joint_position_frames({'LJ2': 0.3, 'LJ1': 0.2}, t)
    moved = {j for j, _, _ in check_joint_frames_within_limits(frames)}
    assert moved == {'LJ1'}
    assert not any(
        f.bus == SILENT.bus and f.msg.arbitration_id & 0x1F == SILENT.module_id for f in frames
    )
    reports = {r.name: r for r in core.diagnostics(t)}
    assert (
        reports['can_bridge: arm'].level == ERROR and 'LJ2' in reports['can_bridge: arm'].message
    )
    assert reports['can_bridge: motion'].level == OK
    assert reports[f'can_bridge: powercube/LJ2/{SILENT.bus}:{SILENT.module_id}'].level == ERROR


def test_a_second_silent_module_is_added_and_only_recover_with_all_answering_clears():
    core, dev, t = healthy_core()
    t = go_silent(core, dev, t)
    other = CFG.powercube.joint('RJ4').modules[0]
    t = go_silent(core, dev, t, {KEY, (other.bus, other.module_id)})
    reason, joints = core.arm_fault(t)
    assert joints == ['LJ2', 'RJ4'] and reason.index('LJ2') < reason.index('RJ4'), reason
    ok, why = core.arm_recover_status(t)
    assert not ok and 'LJ2' in why and 'RJ4' in why
    # answering again does not clear it, nor lets commands through to it
    t += 0.002
    dev.feed(t)
    assert core.arm_fault(t)[1] == ['LJ2', 'RJ4']
    assert core.joint_position_frames({'LJ2': 0.3}, t) == []
    ok, _ = core.arm_recover_status(t)
    assert ok
    startup = core.arm_fault_startup_frames()
    assert {(f.bus, f.msg.arbitration_id & 0x1F) for f in startup} == {
        KEY,
        (other.bus, other.module_id),
    }
    core.clear_arm_fault()
    assert core.arm_fault(t) == ('', [])
    assert core.joint_position_frames({'LJ2': 0.3}, t) != []


def test_a_module_never_heard_keeps_motion_inhibited_and_is_no_arm_fault():
    core, dev, _ = healthy_core()
    fresh = type(core)(CFG, clock=lambda: 0.0)
    dev.core = fresh
    t = 0.0
    for _ in range(CFG.imu.kalman.init_samples + 20):
        t += 0.002
        feed_all_but(dev, t)
    assert not fresh.motion_allowed(t)  # required and never heard: the start-up waits
    assert fresh.arm_fault(t) == ('', [])
    assert 'LJ2' not in fresh.joint_state(t).names


def answer_polls(rig, dt, silent=()):
    """Every module's position reply, but those in `silent`, `dt` after the last frame."""
    rig.t += dt
    for joint in CFG.powercube.joints:
        for m in joint.modules:
            if (m.bus, m.module_id) not in silent:
                rig.frame(m.bus, msg(0x0A0 + m.module_id, bytes([0x0A, 0x3C]) + bytes(4)))


def test_the_runtime_reports_the_arm_fault_once_and_recovers_it_only_once_all_answer():
    rig = Rig()
    try:
        answer_polls(rig, 0.01)
        assert rig.runtime.arm_fault_changed() == ('', [])
        assert rig.runtime.arm_fault_changed() is None
        for _ in range(int(CFG.powercube.silence_timeout_s / 0.04) + 2):
            answer_polls(rig, 0.04, {KEY})
        fault = rig.runtime.arm_fault_changed()
        assert fault is not None and fault[1] == ['LJ2'], fault
        assert rig.runtime.arm_fault_changed() is None
        ok, text = rig.runtime.recover()
        assert not ok and 'not answering' in text and 'arm fault still latched' in text, text
        assert rig.runtime.arm_fault_changed() is None  # still latched, unchanged
        answer_polls(rig, 0.04)
        rig.sent(SILENT.bus)
        ok, text = rig.runtime.recover()
        assert ok and 'arm recovered from' in text, text
        resent = {m.arbitration_id for m in rig.sent(SILENT.bus)}
        assert resent == {0x0E0 + SILENT.module_id}  # its start-up, to it alone
        assert rig.runtime.arm_fault_changed() == ('', [])
    finally:
        rig.close()
