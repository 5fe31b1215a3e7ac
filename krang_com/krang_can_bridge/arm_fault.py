"""The CAN bridge core's arm fault: a PowerCube module that answered and then fell silent. A mixin
of BridgeCore (krang_can_bridge.bridge), whose module states it reads.

A balancing robot must not lose its wheels over an arm module: the wheels keep the current the
controller asks for, and the module's joint stays in the joint state at its last measured
position with velocity 0, so the controller goes on balancing on it. That rests on an assumption
(docs/can.md, "An arm module that stops answering"): a PowerCube module runs its last motion
command to its end by itself and then holds its position; nothing in our kit documents what a
module does when its bus goes quiet. The fault says the joint is held, not measured.

The fault latches on the first module that falls silent (its silence timeout after its last
answer) and names it and its joint; later ones are added to the reason. A module never heard from
is no arm fault: it keeps the motion inhibited as a required device (the start-up waits for it).
Joint commands to a joint with a module named in the fault produce no frames until the fault is
cleared; the other joints are commanded as usual. A module that answers again does not clear the
fault: only `clear_arm_fault` does, which the node's recover calls once `arm_recover_status` says
every module answers, after sending those modules their start-up frames again.
"""

from __future__ import annotations

import logging

from krang_can_bridge.protocols import powercube as pc
from krang_can_bridge.snapshots import BusFrame

logger = logging.getLogger('krang_can_bridge')


class ArmFaults:
    """BridgeCore's arm fault (see the module docstring). Needs `_arm_fault_modules = {}` (module
    key -> its joint, in the order they fell silent) from BridgeCore's constructor."""

    def _check_modules(self, now: float) -> None:
        """Latch every module heard from that is silent at `now`."""
        for key, st in self._modules.items():
            if (
                key not in self._arm_fault_modules
                and st.device.last_seen is not None
                and st.device.silent(now)
            ):
                self._arm_fault_modules[key] = st.joint.joint
                logger.error(
                    f'arm fault: {self._module_text(key)} not answering; the wheels keep '
                    'balancing, its joint is held at its last position'
                )

    def _module_text(self, key) -> str:
        st = self._modules[key]
        return f'arm module {st.device.name} ({st.joint.joint})'

    def arm_fault(self, now: float | None = None) -> tuple[str, list[str]]:
        """(reason, joints) of the latched arm fault, ('', []) when none; the first module to
        fall silent comes first."""
        self._check_modules(self._now(now))
        return self._arm_reason()

    def _arm_reason(self) -> tuple[str, list[str]]:
        keys = list(self._arm_fault_modules)
        if not keys:
            return '', []
        reason = f'{self._module_text(keys[0])} not answering'
        if len(keys) > 1:
            reason += '; also ' + ', '.join(self._module_text(k) for k in keys[1:])
        joints = list(dict.fromkeys(self._arm_fault_modules.values()))
        return reason, joints

    def arm_fault_blocks(self, joint) -> bool:
        """Whether a joint (its BodyJointConfig) has a module named in the arm fault."""
        return any((m.bus, m.module_id) in self._arm_fault_modules for m in joint.modules)

    def arm_recover_status(self, now: float | None = None) -> tuple[bool, str]:
        """(True, '') once every module answers (none silent); (False, which do not)."""
        now = self._now(now)
        self._check_modules(now)
        silent = [st.device.name for st in self._modules.values() if st.device.silent(now)]
        return (False, ', '.join(silent) + ' not answering') if silent else (True, '')

    def arm_fault_startup_frames(self) -> list[BusFrame]:
        """The start-up frames (commands.startup_frames) of the modules named in the fault: one
        that lost its power lost what the start-up set."""
        keys = set(self._arm_fault_modules)
        return [
            f
            for f in self.startup_frames()
            if (f.bus, f.msg.arbitration_id & pc.MODULE_ID_MASK) in keys
        ]

    def clear_arm_fault(self) -> None:
        """Unlatch (only after arm_recover_status said True: see the node's recover service)."""
        if self._arm_fault_modules:
            reason, _ = self._arm_reason()
            logger.warning(f'arm fault cleared by recover: {reason}')
        self._arm_fault_modules.clear()
