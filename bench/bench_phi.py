"""phi(q) throughput: batched numpy kinematics vs pinocchio one pose at a time. Target >= 100,000
poses/s.

.venv/bin/python bench/bench_phi.py
"""

import time

import numpy as np
import pinocchio as pin

from krang_model.com import phi
from krang_model.robot import load_krang


def main():
    robot = load_krang()
    rng = np.random.default_rng(0)
    n = 100_000
    q_base = rng.uniform(-2, 0.5, n)
    joints = rng.uniform(np.maximum(robot.lower, -np.pi), np.minimum(robot.upper, np.pi), (n, 16))
    phi(robot, q_base[:100], joints[:100])  # warm-up
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        for start in range(0, n, 20_000):
            phi(robot, q_base[start : start + 20_000], joints[start : start + 20_000])
        best = min(best, time.perf_counter() - t0)
    batched = n / best

    # reference: pinocchio frame kinematics per pose (what a straightforward phi would call)
    data = robot.model.createData()
    frame_ids = [robot.model.getFrameId(f.name, pin.FrameType.BODY) for f in robot.body_frames]
    m = 2000
    t0 = time.perf_counter()
    for i in range(m):
        pin.framesForwardKinematics(robot.model, data, robot.pin_configuration(joints[i]))
        rows = [
            np.concatenate(([data.oMf[f].translation[1]], data.oMf[f].rotation[1]))
            for f in frame_ids
        ]
    per_pose = m / (time.perf_counter() - t0)
    print(f'phi batched (numpy, 20k-pose batches): {batched:,.0f} poses/s  (target >= 100,000)')
    print(f'pinocchio per pose (framesForwardKinematics + frames): {per_pose:,.0f} poses/s')
    print(f'ratio batched / per-pose: {batched / per_pose:.1f}x')
    del rows


if __name__ == '__main__':
    main()
