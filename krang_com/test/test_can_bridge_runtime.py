"""BridgeRuntime without ROS or DDS: the time base, the held wheel sample, the drives' start-up and
the recovery from a latched fault, over python-can's in-process virtual buses and a clock the test
sets. Device frames are built by hand from docs/can.md's layouts."""

import math
import struct
import threading
import time
import uuid

import can
import pytest

from krang_can_bridge.config import load_devices
from krang_can_bridge.protocols import amc as amc_proto
from krang_can_bridge.runtime import BridgeRuntime
from krang_can_bridge.sample_clock import SIM_TIME_SLACK_S, TimeBase
from krang_core import names

CFG = load_devices()
OPERATION_ENABLED, FAULT = 0x0027, 0x0008
DMU_PERIOD = 0.04  # a 25 Hz DMU: it holds wheel samples (faster than 1 / IMU_HOLD_MAX_S)
JOINTS = [d.joint for d in CFG.wheels.drives]


def msg(aid, data):
    return can.Message(arbitration_id=aid, data=bytes(data), is_extended_id=False)


class Rig:
    """A runtime on virtual buses, its clock, what it published, and a listener on each bus."""

    def __init__(self, run_startup=None, amc_startup=False, recover_timeout_s=1.0):
        self.t = 10.0
        channels = {b: f'runtime-{uuid.uuid4().hex}' for b in CFG.buses_in_use()}
        buses = {b: can.Bus(interface='virtual', channel=c) for b, c in channels.items()}
        self.listen = {b: can.Bus(interface='virtual', channel=c) for b, c in channels.items()}
        self.published = []
        kwargs = {} if run_startup is None else {'run_startup': run_startup}
        self.runtime = BridgeRuntime(
            CFG,
            buses,
            publish=lambda topic, message: self.published.append(message) or True,
            stamp=lambda seconds: seconds,
            encode_imu=lambda imu, stamp: ('imu', stamp),
            encode_joints=lambda joints, stamp: (
                'joints',
                dict(zip(joints.names, joints.positions))['JLWheel'],
            ),
            time_base=TimeBase(sim_clock=lambda: self.t),
            amc_startup=amc_startup,
            recover_timeout_s=recover_timeout_s,
            **kwargs,
        )
        self.seq = 0

    def close(self):
        if hasattr(self, '_loop'):
            self._looping.set()
            self._loop.join()
        if hasattr(self, '_reporter'):
            self._reporting.set()
            self._reporter.join()
        self.runtime.close()
        for bus in self.listen.values():
            bus.shutdown()

    def frame(self, bus, m, dt=0.0):
        self.t += dt
        return self.runtime.on_received(bus, m)

    def dmu(self, dt=0.0, pitch=-0.9):
        """One DMU sample (rates, then accelerations, of one sequence number) at rest."""
        m, g_lsb = CFG.imu.mount_angle_rad, 9.80665 * 0.0003
        f = (
            9.81 * math.sin(pitch) * math.cos(m),
            -9.81 * math.sin(pitch) * math.sin(m),
            9.81 * math.cos(pitch),
        )
        rates = [round(x / math.radians(0.008)) for x in CFG.imu.gyro_bias_rad_s]
        self.frame(CFG.imu.bus, msg(0x40, struct.pack('<hhhBB', *rates, 0, self.seq)), dt)
        accel = [round(x / g_lsb) for x in f]
        self.frame(CFG.imu.bus, msg(0x50, struct.pack('<hhhBB', *accel, 0, self.seq)))
        self.seq = (self.seq + 1) & 0xFF

    def ids(self, joint):
        return self.runtime.core.wheel_state(joint).codec.ids

    def wheels(self, counts=0, dt=0.0, status=OPERATION_ENABLED):
        """Position, velocity and current TPDOs of both drives: one wheel sample."""
        self.t += dt
        for drive in CFG.wheels.drives:
            ids = self.ids(drive.joint)
            bus = CFG.wheels.bus
            self.frame(bus, msg(ids[amc_proto.TPDO_POSITION], struct.pack('<Hi', status, counts)))
            self.frame(bus, msg(ids[amc_proto.TPDO_VELOCITY], struct.pack('<Hi', status, 0)))
            self.frame(bus, msg(ids[amc_proto.TPDO_CURRENT], struct.pack('<Hh', status, 0)))

    def statusword(self, joint, status, dt=0.0):
        data = struct.pack('<H', status)
        self.frame(CFG.wheels.bus, msg(self.ids(joint)[amc_proto.TPDO_STATUSWORD], data), dt)

    def report_status(self, status):
        """From now on, both drives' statusword TPDOs every 5 ms (in a thread), `status` once the
        drive's start-up ran (`status_of`), and the clock advancing with them."""
        self.status_of = {}
        self._reporting = threading.Event()

        def run():
            while not self._reporting.wait(0.005):
                for joint, value in list(self.status_of.items()):
                    self.statusword(joint, value, dt=0.005)

        self._reporter = threading.Thread(target=run, daemon=True)
        self._reporter.start()
        return lambda drive: self.status_of.__setitem__(drive.joint, status)

    def run_command_loop(self):
        """From now on, the wheel command loop's timer every 5 ms of the clock (in a thread), as
        the node's executor runs it."""
        self._looping = threading.Event()

        def run():
            while not self._looping.wait(0.005):
                self.t += 0.005
                self.runtime.time.frame_seen(self.t)
                self.runtime.wheel_watchdog()

        self._loop = threading.Thread(target=run, daemon=True)
        self._loop.start()

    def kinds(self):
        return [m[0] for m in self.published]

    def sent(self, bus):
        out = []
        while (m := self.listen[bus].recv(0.0)) is not None:
            out.append(m)
        return out


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_time_base_on_the_wall_clock():
    base = TimeBase()
    assert not base.simulated
    assert base.device_time() == pytest.approx(base.frame_time(), abs=0.01)
    assert base.stamp_seconds(0.0) == pytest.approx(base.stamp_offset)


def test_time_base_in_simulation_checks_at_most_the_slack_past_the_newest_frame():
    now = [5.0]
    base = TimeBase(sim_clock=lambda: now[0])
    base.frame_seen(5.0)
    now[0] = 5.01
    assert base.device_time() == 5.01
    now[0] = 7.0  # the clock ran ahead of the frames still queued
    assert base.device_time() == 5.0 + SIM_TIME_SLACK_S
    base.frame_seen(6.99)
    assert base.device_time() == 7.0
    base.frame_seen(1.0)  # an older frame moves nothing back
    assert base.newest_frame == 6.99
    assert base.stamp_seconds(3.0) == 3.0


def test_frames_before_the_simulators_clock_are_not_put_at_time_zero():
    """In simulation the bridge may hear the devices before the simulator's first /clock
    message (ROS time 0 until then). Stamped 0, the modules' answers looked silent since the
    clock's first reading, the simulator's time since its start: an arm fault for every module at
    start-up. Frames before the clock are left out; the first ones after it count."""
    rig = Rig()
    try:
        rig.t = 0.0  # no /clock message yet
        module = CFG.powercube.joint('LJ2').modules[0]
        answer = msg(0x0A0 + module.module_id, bytes([0x0A, 0x3C]) + struct.pack('<f', 0.25))
        assert not rig.runtime.time.known()
        rig.frame(module.bus, answer)
        rig.wheels()
        assert rig.published == []
        rig.t = 3.0  # the clock's first reading: the simulator has run for 3 s
        assert rig.runtime.time.known()
        rig.wheels()
        assert rig.runtime.core.arm_fault(rig.runtime.time.device_time()) == ('', [])
        rig.frame(module.bus, answer)  # heard from now on; silent only past its timeout
        rig.wheels(dt=CFG.powercube.silence_timeout_s + 0.01)
        reason, joints = rig.runtime.core.arm_fault(rig.runtime.time.device_time())
        assert joints == ['LJ2'], reason
    finally:
        rig.close()


def start_streaming(rig):
    for _ in range(CFG.imu.kalman.init_samples + 50):
        rig.dmu(DMU_PERIOD)
        if rig.kinds().count('imu') >= 2:
            return
    raise AssertionError(f'the IMU filter never published: {rig.published}')


def test_a_wheel_sample_waits_for_the_next_dmu_sample_while_the_dmu_streams(rig):
    start_streaming(rig)
    rig.published.clear()
    rig.dmu(DMU_PERIOD)
    rig.wheels(1000, dt=0.3 * DMU_PERIOD)
    assert rig.kinds() == ['imu'], 'a wheel sample went out between samples'
    first = rig.runtime.core.wheel_state('JLWheel').position
    rig.dmu(0.7 * DMU_PERIOD)
    assert rig.kinds()[1:] == ['joints', 'imu']
    assert rig.published[1][1] == first
    # two wheel samples before one DMU sample: only the newer goes out
    rig.wheels(2000, dt=0.3 * DMU_PERIOD)
    rig.wheels(3000)
    newer = rig.runtime.core.wheel_state('JLWheel').position
    assert newer != first
    rig.dmu(0.7 * DMU_PERIOD)
    assert rig.kinds()[3:] == ['joints', 'imu']
    assert rig.published[3][1] == newer
    assert rig.runtime.published == {
        names.IMU: rig.kinds().count('imu') + 2,
        names.JOINT_STATES: 2,
    }
    # the DMU stops: after 1.5 of its periods each wheel sample goes out at once
    rig.published.clear()
    rig.wheels(4000, dt=2.0 * DMU_PERIOD)
    rig.wheels(5000)
    assert rig.kinds() == ['joints', 'joints']


def test_without_the_dmu_wheel_samples_go_out_as_they_complete(rig):
    rig.wheels(100, dt=0.002)
    rig.wheels(200, dt=0.002)
    assert rig.kinds() == ['joints', 'joints']


def test_a_frame_that_latches_a_fault_sends_zero_current_at_once_and_is_reported_once(rig):
    assert rig.runtime.fault_changed() == ''
    assert rig.runtime.fault_changed() is None
    rig.sent(CFG.wheels.bus)
    node_id = CFG.wheels.drives[0].node_id
    rig.frame(CFG.wheels.bus, msg(0x80 + node_id, [0x10, 0x23, 0, 0, 0, 0, 0, 0]), 0.001)
    reason = rig.runtime.core.fault_reason
    assert 'EMCY 0x2310' in reason
    currents = {m.arbitration_id for m in rig.sent(CFG.wheels.bus)}
    assert len(currents) == len(CFG.wheels.drives)  # one current frame per drive, zero
    assert rig.runtime.fault_changed() == reason
    assert rig.runtime.fault_changed() is None


class Startup:
    """A stand-in for protocols.amc_canopen.run_startup: each call answers from `script` (a list of
    mismatches, or an exception to raise) and may run `then` (the drive's answer on the bus)."""

    def __init__(self, script, then=None):
        self.script, self.then, self.calls = list(script), then, []

    def __call__(self, network, drive, wheels, sdo_timeout_s, armed=None):
        self.calls.append(drive.joint)
        step = self.script.pop(0) if len(self.script) > 1 else self.script[0]
        if isinstance(step, Exception):
            raise step
        if self.then is not None:
            self.then(drive)
        return step


def test_start_up_enables_each_drive_and_retries_a_failed_transfer():
    startup = Startup([TimeoutError('no SDO response'), []])
    rig = Rig(run_startup=startup, amc_startup=True)
    try:
        startup.then = rig.report_status(OPERATION_ENABLED)
        assert set(rig.runtime.startup_status.values()) == {'pending'}
        assert rig.runtime.core.inhibits  # no motion before the start-up
        rig.runtime.start(retry_s=0.01)
        time.sleep(0.3)
        assert startup.calls == []  # the drives wait for a steady command loop
        rig.run_command_loop()
        rig.runtime.startup_thread.join(10.0)
        assert rig.runtime.startup_status == dict.fromkeys(JOINTS, 'enabled')
        assert startup.calls[0] == startup.calls[1] == CFG.wheels.drives[0].joint
        assert not rig.runtime.core.inhibits
    finally:
        rig.close()


def test_constants_that_disagree_inhibit_motion():
    rig = Rig(run_startup=Startup([['Kt: drive 0.1, config 0.2']]), amc_startup=True)
    try:
        drive = CFG.wheels.drives[0]
        rig.runtime.bring_up_drive(drive, retry_s=0.01)
        assert rig.runtime.startup_status[drive.joint].startswith('constants mismatch: Kt')
        assert 'Kt' in rig.runtime.core.inhibits[f'startup/{drive.joint}']
    finally:
        rig.close()


def test_recover_without_a_fault_runs_nothing():
    startup = Startup([[]])
    rig = Rig(run_startup=startup)
    try:
        assert rig.runtime.recover() == (True, 'no drive fault latched')
        assert startup.calls == []
    finally:
        rig.close()


def latch_fault(rig):
    node_id = CFG.wheels.drives[1].node_id
    rig.frame(CFG.wheels.bus, msg(0x80 + node_id, [0x10, 0x23, 0, 0, 0, 0, 0, 0]), 0.001)
    assert rig.runtime.core.fault_reason


def test_recover_reruns_each_drive_start_up_and_unlatches_once_all_are_enabled():
    startup = Startup([[]])
    rig = Rig(run_startup=startup)
    try:
        startup.then = rig.report_status(OPERATION_ENABLED)
        latch_fault(rig)
        ok, text = rig.runtime.recover()
        assert ok and text.startswith('recovered from: ')
        assert startup.calls == JOINTS
        assert not rig.runtime.core.fault_reason
    finally:
        rig.close()


def test_recover_is_refused_while_a_drive_stays_in_fault():
    startup = Startup([[]])
    rig = Rig(run_startup=startup)
    try:
        startup.then = rig.report_status(FAULT)
        latch_fault(rig)
        ok, text = rig.runtime.recover()
        assert not ok and 'still reports FAULT' in text and 'fault still latched' in text
        assert rig.runtime.core.fault_reason
    finally:
        rig.close()


def test_recover_reports_a_failed_start_up_and_keeps_the_fault():
    rig = Rig(run_startup=Startup([TimeoutError('no SDO response')]))
    try:
        latch_fault(rig)
        ok, text = rig.runtime.recover()
        assert not ok and 'fault reset and enable failed' in text and 'TimeoutError' in text
    finally:
        rig.close()


def test_recover_keeps_the_wheel_command_loop_going():
    startup = Startup([[]])
    rig = Rig(run_startup=startup)
    try:
        report = rig.report_status(OPERATION_ENABLED)
        startup.then = lambda drive: (time.sleep(0.1), report(drive))
        latch_fault(rig)
        rig.sent(CFG.wheels.bus)
        ok, _ = rig.runtime.recover_keeping_alive()
        assert ok
        # zero current went on going out while the start-up ran (at the command rate)
        assert len(rig.sent(CFG.wheels.bus)) >= 2 * len(CFG.wheels.drives)
    finally:
        rig.close()


def test_diagnostics_name_the_start_up_and_the_samples():
    rig = Rig()
    try:
        reports = {r.name: r for r in rig.runtime.diagnostics()}
        for joint in JOINTS:
            assert reports[f'can_bridge: amc/{joint} start-up'].message == 'pending'
        assert names.IMU in reports['can_bridge: samples published'].values
    finally:
        rig.close()


def test_a_start_up_whose_drive_does_not_report_enabled_is_not_taken_for_done():
    """The sequence ran, but the drive (disabled on the way, e.g. by its watchdog) reports
    SWITCH_ON_DISABLED: not started, motion stays inhibited, and the start-up runs again."""
    startup = Startup([[]])
    rig = Rig(run_startup=startup, amc_startup=True, recover_timeout_s=0.2)
    try:
        report = rig.report_status(0x0040)
        startup.then = report
        drive = CFG.wheels.drives[0]
        worker = threading.Thread(target=rig.runtime.bring_up_drive, args=(drive, 0.01))
        worker.start()
        deadline = time.monotonic() + 5.0
        while len(startup.calls) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        status = rig.runtime.startup_status[drive.joint]
        assert status.startswith('failed: StartupNotVerified') and 'SWITCH_ON_DISABLED' in status
        assert f'startup/{drive.joint}' in rig.runtime.core.inhibits
        assert not rig.runtime.core.wheel_state(drive.joint).started
        rig.status_of.clear()
        startup.then = rig.report_status(OPERATION_ENABLED)
        worker.join(5.0)
        assert rig.runtime.startup_status[drive.joint] == 'enabled'
        assert f'startup/{drive.joint}' not in rig.runtime.core.inhibits
    finally:
        rig.close()


def boot_up(rig, joint):
    node_id = CFG.wheels.drive(joint).node_id
    rig.frame(CFG.wheels.bus, msg(0x700 + node_id, [0x00]), 0.001)


def test_a_drive_that_reboots_latches_a_fault_that_only_its_start_up_again_clears():
    startup = Startup([[]])
    rig = Rig(run_startup=startup)
    try:
        startup.then = rig.report_status(OPERATION_ENABLED)
        for drive in CFG.wheels.drives:
            rig.runtime.start_drive(drive)
        assert not rig.runtime.core.fault_reason
        rig.sent(CFG.wheels.bus)
        boot_up(rig, 'JRWheel')
        reason = rig.runtime.core.fault_reason
        assert 'JRWheel' in reason and 'rebooted' in reason
        assert len(rig.sent(CFG.wheels.bus)) == len(JOINTS)  # zero current on both, at once
        assert not rig.runtime.core.motion_allowed()
        startup.calls.clear()
        ok, text = rig.runtime.recover()
        assert ok, text
        assert startup.calls == JOINTS  # the whole start-up again, the rebooted drive's included
        assert not rig.runtime.core.fault_reason
    finally:
        rig.close()


def test_a_boot_up_during_the_start_up_voids_it():
    rig = Rig()
    try:
        report = rig.report_status(OPERATION_ENABLED)

        def rebooting(drive):
            boot_up(rig, drive.joint)  # power-cycled after its objects were written
            report(drive)

        rig.runtime._run_startup = Startup([[]], then=rebooting)
        with pytest.raises(RuntimeError, match='rebooted during its start-up'):
            rig.runtime.start_drive(CFG.wheels.drives[0])
        assert not rig.runtime.core.wheel_state(CFG.wheels.drives[0].joint).started
        assert not rig.runtime.core.fault_reason  # not started yet: no fault, a retry
    finally:
        rig.close()


def test_an_nmt_state_other_than_operational_of_a_started_drive_latches_a_fault(rig):
    rig.runtime.core.drive_started('JLWheel', True)
    node_id = CFG.wheels.drive('JLWheel').node_id
    rig.frame(CFG.wheels.bus, msg(0x700 + node_id, [0x05]), 0.001)  # a heartbeat: operational
    assert not rig.runtime.core.fault_reason
    rig.frame(CFG.wheels.bus, msg(0x700 + node_id, [0x7F]), 0.001)
    assert 'PRE-OPERATIONAL' in rig.runtime.core.fault_reason


class Refusing:
    """A bus whose send raises (a full transmit queue, a bus-off controller) while `refusing`, or
    on every `every`-th frame."""

    def __init__(self, bus):
        self.bus, self.refusing, self.every, self.sends = bus, False, 0, 0

    def send(self, msg, timeout=None):
        self.sends += 1
        if self.refusing or (self.every and self.sends % self.every == 0):
            raise can.CanOperationError('Failed to transmit: No buffer space available')
        self.bus.send(msg, timeout=timeout)

    def __getattr__(self, name):
        return getattr(self.bus, name)


def send_for(rig, seconds):
    """The wheel command loop for `seconds` (wall time: send failures are timed on it)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rig.runtime.wheel_effort([1.0, 1.0])
        time.sleep(0.005)


@pytest.mark.parametrize('pattern', ['intermittent', '200 ms', 'for good'])
def test_a_bus_that_refuses_frames(rig, pattern):
    """Intermittent failures are counted; sends failing for longer than the command timeout
    inhibit motion (zero current is what the bridge then tries to send) with the reason in
    diagnostics, until a frame goes out again."""
    bus = CFG.wheels.bus
    refusing = rig.runtime.buses[bus] = Refusing(rig.runtime.buses[bus])
    core, key = rig.runtime.core, f'send/{bus}'
    if pattern == 'intermittent':
        refusing.every = 3
        send_for(rig, 0.3)
        assert key not in core.inhibits and rig.runtime.send_failures.counts[bus] >= 10
        report = {r.name: r for r in rig.runtime.diagnostics()}[f'can_bridge: bus {bus} I/O']
        assert report.level == 1 and 'send errors' in report.message
        return
    refusing.refusing = True
    send_for(rig, 0.2 if pattern == '200 ms' else 0.5)
    assert 'refused' in core.inhibits[key] and 'No buffer space' in core.inhibits[key]
    report = {r.name: r for r in rig.runtime.diagnostics()}[f'can_bridge: bus {bus} I/O']
    assert report.level == 2 and 'every send failing' in report.message
    if pattern == '200 ms':
        refusing.refusing = False
        send_for(rig, 0.02)
        assert key not in core.inhibits
        report = {r.name: r for r in rig.runtime.diagnostics()}[f'can_bridge: bus {bus} I/O']
        assert report.level == 1  # the errors stay counted
