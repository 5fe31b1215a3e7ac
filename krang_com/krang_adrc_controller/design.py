"""The balancing controller's model of the pose it holds: the CoM offset and LQR(q) of the
reference pose and beta, redone as the pose changes (module docstring of controller, stage 4),
and the ADRC and balance-point observer they parametrise. A mixin of controller.BalanceController,
whose state it reads and sets."""

from __future__ import annotations

import math

import numpy as np

from krang_model.com import base_regressor
from krang_model.wip import linearize, reduce_pose

from .adrc import AdrcController
from .balance_point import BalancePointObserver

#: ESO bandwidth of the balance-point observer when the ADRC runs the authors' gains, rad/s
BALANCE_POINT_OMEGA_O = 20.0


class PoseDesign:
    """BalanceController's design half (see the module docstring)."""

    def expected_rest_offset(self) -> float:
        """x - x_ref (m) where ADRC/LQR come to rest for a CoM-angle error of 1 rad:
        -F_th0/F_x0."""
        d = self._design
        return -d['F_theta'][0] / d['F_x'][0]

    def _body(self, pose, beta):
        memo = self._body_memo
        if memo is not None and memo[0] is pose and memo[1] == self._beta_version:
            return memo[2]
        body = reduce_pose(self.robot, pose, beta)
        self._body_memo = (pose, self._beta_version, body)
        return body

    def _linearize(self, pose, beta):
        return linearize(self._body(pose, beta), self.drive)

    def _offset_for(self, joints) -> float:
        m = base_regressor(self.robot, np.asarray(joints, float)[None])[0] @ self._beta
        return math.atan2(-m[2], m[1])

    def _redesign(self, pose) -> None:
        """Full update for a (new) reference pose: offset, LQR(q), ADRC gains."""
        pose = np.array(pose, dtype=float)
        same_pose = self._pose is not None and np.array_equal(pose, self._pose)
        self._pose = pose
        body = self._body(pose, self._beta)
        self._shift_offset(body.com_offset_full, same_pose)
        d = self.gains.design(pose, self._beta)
        self._design = d
        self.redesigns += 1
        cfg = self.config
        if self.adrc is None:
            self.adrc = AdrcController.from_design(
                d, self.drive, sample_period_s=self.h, config=cfg.adrc
            )
            if cfg.balance_point.enabled:
                self.balance_point = BalancePointObserver(
                    self.h, cfg.adrc.eso.omega_o or BALANCE_POINT_OMEGA_O, cfg.balance_point
                )
            self._balance_point_active = (
                self.balance_point is not None and cfg.adrc.use_disturbance_rejection
            )
        else:
            self.adrc.set_gains(d['F_x'], d['F_theta'], d['b_x'], d['b_theta'])
        if self.balance_point is not None:
            self.balance_point.set_model(d['A'], d['B'])

    def _shift_offset(self, offset: float, same_pose: bool = False) -> None:
        """New theta offset. The theta-ESO's estimate moves with it (bumpless): a model change is
        a step in the measured theta that no motion caused, and must not read as an acceleration.
        With the balance-point observer the ADRC sees theta - delta_hat: it moves by what delta_hat
        does not take."""
        delta = offset - self._offset
        self._offset = offset
        if not delta:
            return
        step = delta
        if self.balance_point is not None:
            before = self.balance_point.delta
            self.balance_point.shift(delta, same_pose)
            if self.adrc.use_disturbance_rejection:
                step -= self.balance_point.delta - before
        if self.adrc is not None:
            self.adrc.shift_theta(step)

    def set_disturbance_rejection(self, enabled: bool) -> None:
        """ADRC (True) or plain LQR (False) in BALANCE."""
        self.config = self.config.override({'adrc.use_disturbance_rejection': bool(enabled)})
        if self.adrc is not None:
            self.adrc.set_disturbance_rejection(enabled)
        self._balance_point_active = self.balance_point is not None and bool(enabled)

    def _track_pose(self, t, joints, moving) -> None:
        if self._pose is None:
            self._redesign(joints)
            return
        if moving:
            if not self._moving:
                self._moving = True
                self._t_offset = self._t_gain = -math.inf
            if t - self._t_gain >= self.config.lqr.gain_update_period_s:
                self._t_gain = self._t_offset = t
                self._redesign(joints)
            elif t - self._t_offset >= self.config.lqr.pose_update_period_s:
                self._t_offset = t
                self._shift_offset(self._offset_for(joints))
            return
        if self._moving:
            self._moving = False
            self._t_still = t
            self._redesign(joints)
            return
        # settled: called every pose_check_period_s by step()
        if float(np.max(np.abs(joints - self._pose))) > self.config.lqr.pose_tol_rad:
            self._redesign(joints)
