"""The CAN bridge core's commands: every frame it sends, each within the configured limits.

Wheel currents are clamped to the configured limit and the drive's peak, joint targets to the joint
limits (in module coordinates, after float32 rounding), module speeds and accelerations to the
module's datasheet limits; a NaN/inf command is rejected with a logged reason (the two wheel
efforts are one command: unless both are finite, both wheels get zero current). A mixin of
BridgeCore (krang_can_bridge.bridge), whose state it reads.
"""

from __future__ import annotations

import logging
import math
from typing import Mapping

from krang_can_bridge.config import BodyJointConfig, PowerCubeModuleConfig
from krang_can_bridge.protocols import amc as amc_proto
from krang_can_bridge.protocols import powercube as pc
from krang_can_bridge.snapshots import BusFrame, float32_within

# The watchdog timer sends only when no current frame went out for this many refresh periods
# (1 / wheels.command_rate_hz): commands that flow at least that often are never doubled.
WATCHDOG_QUIET_PERIODS = 2.0


class CommandFrames:
    """BridgeCore's command half: wheel currents, joint moves, the drives' watchdog frames, the
    PowerCube polls and start-up, the DMU stream toggle."""

    # ---- wheel commands -------------------------------------------------------------------------
    def wheel_current_limit_a(self, joint: str) -> float:
        """The drive train's current limit, or the drive's peak if lower."""
        return min(
            self.config.wheels.drivetrain.current_limit,
            self._wheels[joint].codec.drive.peak_current_a,
        )

    def _reject(self, reason: str, now: float) -> None:
        c = self.counters
        c.rejected_commands += 1
        c.last_rejection, c.last_rejection_at = reason, now
        self._log(f'reject:{reason.split(":")[0]}', f'rejected command: {reason}')

    def _wheel_efforts(self, efforts, now: float) -> tuple[float, ...] | None:
        """The efforts as floats if they are one valid command (one finite value per wheel), else
        None with the rejection recorded."""
        joints = self.config.wheel_joint_names
        try:
            values = list(efforts)
        except TypeError:
            values = None
        if values is None or len(values) != len(joints):
            n = 'no sequence' if values is None else f'{len(values)} values'
            self._reject(f'wheels: need [{", ".join(joints)}], got {n} -> 0 A on both', now)
            return None
        out = []
        for joint, v in zip(joints, values):
            try:
                x = float(v)
            except (TypeError, ValueError, OverflowError):
                x = math.nan
            if not math.isfinite(x):
                self._reject(f'wheels: {joint} effort {v!r} is not finite -> 0 A on both', now)
                return None
            out.append(x)
        return tuple(out)

    def wheel_current_frames(
        self, effort_left_Nm: float, effort_right_Nm: float, now: float | None = None
    ) -> list[BusFrame]:
        """RPDO current frames for efforts at the wheels [N m], clamped; zero current on both when
        motion is not allowed or either effort is invalid."""
        now = self._now(now)
        efforts = self._wheel_efforts((effort_left_Nm, effort_right_Nm), now)
        allowed = efforts is not None and self.motion_allowed(now)
        frames = []
        for joint, effort in zip(self.config.wheel_joint_names, efforts or (0.0, 0.0)):
            amps = 0.0
            if allowed:
                requested = self.config.wheels.effort_to_current(effort)
                limit = self.wheel_current_limit_a(joint)
                amps = min(limit, max(-limit, requested))
                if amps != requested:
                    self.counters.clamped_commands += 1
                    self._log(
                        f'clamp{joint}',
                        f'{joint}: {requested:.2f} A clamped to {amps:.2f} A',
                        logging.INFO,
                    )
            frames.append(
                BusFrame(
                    self.config.wheels.bus, self._wheels[joint].codec.encode_current_command(amps)
                )
            )
        return frames

    def set_wheel_effort_command(self, efforts, now: float | None = None) -> None:
        """Remember the latest effort command [left, right] N m (sent by `wheel_command_frames`
        while it is fresh); an invalid one is rejected and replaced by zero on both wheels."""
        now = self._now(now)
        valid = self._wheel_efforts(efforts, now)
        left, right = valid if valid is not None else (0.0, 0.0)
        self._wheel_command = (left, right, now)

    def wheel_command_frames(self, now: float | None = None) -> list[BusFrame]:
        """The current frames of the latest command if younger than command_timeout_s, else zero
        current (sent on each command, and by `wheel_watchdog_frames`)."""
        now = self._now(now)
        self._loop_ran(now)
        self._wheel_sent_at = now
        cmd = self._wheel_command
        if cmd is None or now - cmd[2] > self.config.wheels.command_timeout_s:
            return self.wheel_current_frames(0.0, 0.0, now)
        return self.wheel_current_frames(cmd[0], cmd[1], now)

    def wheel_watchdog_frames(self, now: float | None = None) -> list[BusFrame]:
        """The wheel command loop's timer: zero current once the latest command is stale (older
        than command_timeout_s) or motion is not allowed, repeated every WATCHDOG_QUIET_PERIODS
        refresh periods; [] otherwise. A command in force is never repeated: its frames went out
        with it, the drive holds that current, and a repeat would only be a frame that answers
        no sample (in lockstep simulation sim_krang would take it for the controller's answer
        and run on while the controller is late). Either way the loop counts as running, which
        keeps the drives' watchdog fed."""
        now = self._now(now)
        self._loop_ran(now)
        quiet = WATCHDOG_QUIET_PERIODS / self.config.wheels.command_rate_hz
        if self._wheel_sent_at is not None and now - self._wheel_sent_at < quiet:
            return []
        cmd = self._wheel_command
        in_force = (
            cmd is not None
            and now - cmd[2] <= self.config.wheels.command_timeout_s
            and self.motion_allowed(now)
        )
        return [] if in_force else self.wheel_command_frames(now)

    # ---- joint commands -------------------------------------------------------------------------
    def _module_target(
        self, joint: BodyJointConfig, module: PowerCubeModuleConfig, q: float
    ) -> float:
        lower, upper = joint.module_limits(module)
        return float32_within(module.sign * q, lower, upper)

    def joint_position_frames(
        self, targets: Mapping[str, float], now: float | None = None
    ) -> list[BusFrame]:
        """FRAMP moves to joint targets [rad] (URDF names), clamped; [] when motion is not allowed.

        Each commanded module gets TARGET_VEL and TARGET_ACC (the module type's limits) then
        SET_MOTION FRAMP, like pcio_group_setpos. Unknown names (e.g. the wheels), non-finite
        targets and joints with a module named in the arm fault (it holds where it is) are
        skipped and logged.
        """
        now = self._now(now)
        self._check_modules(now)
        if not self.motion_allowed(now):
            if targets:
                self._log(
                    'joints_blocked', 'joint command dropped: motion not allowed (silent device)'
                )
            return []
        frames = []
        for name, q in targets.items():
            try:
                joint = self.config.powercube.joint(name)
            except KeyError:
                self._log(
                    f'unknown{name}',
                    f'joint command for unknown joint {name!r} ignored',
                    logging.INFO,
                    10.0,
                )
                continue
            if self.arm_fault_blocks(joint):
                self._log(
                    f'armfault{name}',
                    f'{name}: no command, its module is not answering (arm fault)',
                )
                continue
            try:
                q = float(q)
            except (TypeError, ValueError):
                q = math.nan
            if not math.isfinite(q):
                self._reject(f'{name}: non-finite target {q!r} -> no motion', now)
                continue
            if joint.clamp(q) != q:
                self.counters.clamped_commands += 1
                self._log(
                    f'clamp{name}',
                    f'{name}: target {q:.4f} clamped to [{joint.lower}, {joint.upper}]',
                    logging.INFO,
                )
            vel = float32_within(joint.max_velocity_rad_s, 0.0, joint.max_velocity_rad_s)
            acc = float32_within(joint.max_acceleration_rad_s2, 0.0, joint.max_acceleration_rad_s2)
            for m in joint.modules:
                frames += [
                    BusFrame(m.bus, pc.set_param(m.module_id, pc.TARGET_VEL, vel)),
                    BusFrame(m.bus, pc.set_param(m.module_id, pc.TARGET_ACC, acc)),
                    BusFrame(
                        m.bus,
                        pc.set_motion(m.module_id, pc.FRAMP_ACK, self._module_target(joint, m, q)),
                    ),
                ]
        return frames

    def _loop_ran(self, now: float) -> None:
        """The wheel command loop ran at `now`; a gap of more than half the watchdog's
        alive_timeout_s restarts its steady run (`loop_steady_for`)."""
        last = self._command_loop_at
        if last is None or now - last > 0.5 * self.config.wheels.watchdog.alive_timeout_s:
            self._loop_steady_since = now
        self._command_loop_at = now

    def loop_steady_for(self, now: float | None = None) -> float:
        """How long the wheel command loop has run without a gap of half the watchdog's
        alive_timeout_s, up to `now` [s]; 0 before it ran or once it stopped."""
        now = self._now(now)
        last = self._command_loop_at
        if last is None or now - last > 0.5 * self.config.wheels.watchdog.alive_timeout_s:
            return 0.0
        return now - self._loop_steady_since

    def watchdog_frames(self, now: float | None = None) -> list[BusFrame]:
        """The frames the drives' watchdog consumes (the bridge's heartbeat, or a guarding request
        per drive), or [] when the wheel command loop has not run within alive_timeout_s: a beat
        proves the control path is alive, not just that this process is."""
        now = self._now(now)
        wd, bus = self.config.wheels.watchdog, self.config.wheels.bus
        if (
            wd.mechanism == 'none'
            or self._command_loop_at is None
            or now - self._command_loop_at > wd.alive_timeout_s
        ):
            return []
        if wd.mechanism == 'heartbeat':
            return [BusFrame(bus, amc_proto.heartbeat_frame(wd))]
        return [
            BusFrame(bus, amc_proto.guarding_request(d.node_id)) for d in self.config.wheels.drives
        ]

    def poll_frames(self) -> list[BusFrame]:
        """GET_PARAM ACT_FPOS and ACT_FVEL for every module (modules only speak when asked); the
        same frames every time, encoded once."""
        if self._poll_frames is None:
            self._poll_frames = [
                BusFrame(bus, pc.get_param(module_id, param))
                for bus, module_id in self._modules
                for param in (pc.ACT_FPOS, pc.ACT_FVEL)
            ]
        return list(self._poll_frames)

    def startup_frames(self) -> list[BusFrame]:
        """PowerCube start-up: RESET (clears HALT), soft limits MIN/MAX_FPOS in module coordinates
        (as the robot's init script set them), TARGET_VEL/TARGET_ACC. The AMC start-up needs SDO
        replies: see amc_canopen.run_startup."""
        frames = []
        for st in self._modules.values():
            lower, upper = st.joint.module_limits(st.module)
            b, i = st.module.bus, st.module.module_id
            frames += [
                BusFrame(b, pc.simple_command(i, pc.RESET)),
                BusFrame(b, pc.set_param(i, pc.MIN_FPOS, float32_within(lower, lower, upper))),
                BusFrame(b, pc.set_param(i, pc.MAX_FPOS, float32_within(upper, lower, upper))),
                BusFrame(
                    b,
                    pc.set_param(
                        i,
                        pc.TARGET_VEL,
                        float32_within(
                            st.joint.max_velocity_rad_s, 0.0, st.joint.max_velocity_rad_s
                        ),
                    ),
                ),
                BusFrame(
                    b,
                    pc.set_param(
                        i,
                        pc.TARGET_ACC,
                        float32_within(
                            st.joint.max_acceleration_rad_s2, 0.0, st.joint.max_acceleration_rad_s2
                        ),
                    ),
                ),
            ]
        return frames

    def imu_stream_frames(self, now: float | None = None) -> list[BusFrame]:
        """The DMU stream toggle, only after no DMU frame came for stream_toggle_retry_s (it is a
        toggle: sending it to a streaming DMU would stop it, a frozen one included)."""
        now = self._now(now)
        quiet_since = max(
            self._started_at,
            self._imu_frame_at if self._imu_frame_at is not None else -math.inf,
            self._last_stream_toggle if self._last_stream_toggle is not None else -math.inf,
        )
        if now - quiet_since < self.config.imu.stream_toggle_retry_s:
            return []
        self._last_stream_toggle = now
        return [BusFrame(self.config.imu.bus, self.dmu.stream_toggle())]
