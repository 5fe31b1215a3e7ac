"""Real-time factor of the nonlinear WIP simulation at a 1 kHz step. Target >= 200x real time.

.venv/bin/python bench/bench_wip_sim.py
"""

import time

import numpy as np

from krang_model.robot import load_krang
from krang_model.drivetrain import drivetrain
from krang_model.wip import WipDynamics, linearize, reduce_pose
import control


def main():
    robot = load_krang()
    pose = np.array(
        [
            2.2,
            0.07,
            1.0,
            -1.1,
            0.0,
            -1.6,
            0.04,
            1.0,
            -0.02,
            -0.85,
            1.1,
            0.0,
            1.56,
            -0.03,
            -1.05,
            0.02,
        ]
    )
    body = reduce_pose(robot, pose, robot.nominal_beta)
    drive = drivetrain(robot)
    dyn = WipDynamics(body, drive)
    a, b = linearize(body, drive)
    k, _, _ = control.lqr(a, b, np.diag([1e3, 1e3, 1e4, 1e3]), np.array([[1.0]]))
    k = k[0]
    r, upright = drive.wheel_radius, -body.com_offset
    dt, seconds = 1e-3, 60.0
    state = [0.0, upright + 0.05, 0.0, 0.0, 0.0, 0.0]
    t0 = time.perf_counter()
    for _ in range(int(seconds / dt)):
        x = (r * state[0], r * state[2], state[1] - upright, state[3])
        tau = -(k[0] * x[0] + k[1] * x[1] + k[2] * x[2] + k[3] * x[3])
        state = dyn.step(state, 0.5 * tau, 0.5 * tau, dt)
    wall = time.perf_counter() - t0
    print(
        f'simulated {seconds:.0f} s at 1 kHz (semi-implicit Euler, LQR in the loop) in {wall:.2f} '
        f's'
    )
    print(
        f'real-time factor: {seconds / wall:.0f}x  (target >= 200x); final pitch error '
        f'{state[1] - upright:+.2e} rad'
    )
    t0 = time.perf_counter()
    for _ in range(20000):
        state = dyn.step_rk4(state, 0.0, 0.0, dt)
    print(f'RK4 for comparison: {20.0 / (time.perf_counter() - t0):.0f}x real time')


if __name__ == '__main__':
    main()
