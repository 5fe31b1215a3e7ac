"""Closed-loop simulation speed and the balancing controller's per-step cost.

    .venv/bin/python bench/bench_closed_loop.py [--seconds 60] [--repeat 3]

Targets: the closed loop (controller at 500 Hz, physics at 1 kHz, sensor noise on) >= 100x real
time while balancing; the controller step well inside its 2 ms period. Prints best-of-N wall times
and the ratios. While the body joints move, the simulator re-reduces the pose every 20 ms and the
controller updates its CoM offset and LQR(q), so that part runs slower; it is measured separately.
"""

import argparse
import time

from krang_adrc_controller.controller import load_controller_config
from krang_model.beta import load_beta
from krang_model.config import config_path
from krang_model.robot import load_krang
from krang_sim.closed_loop import ClosedLoop
from krang_sim.reduced_plant import ReducedPlant
from krang_sim.scenarios import TABLE2_POSE, run_balance, shifted_beta
from krang_sim.sensors import SensorModel


def best(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seconds', type=float, default=60.0)
    ap.add_argument('--repeat', type=int, default=3)
    args = ap.parse_args(argv)
    robot = load_krang()
    tb = load_beta(config_path('sim_true_beta.yaml'), robot)
    wrong = shifted_beta(robot, tb, TABLE2_POSE, 0.025)
    cfg = load_controller_config()
    period_us = 1e6 / cfg.rate_hz
    print(
        f'controller {cfg.rate_hz:.0f} Hz ({period_us:.0f} us period), physics 1 kHz, sensor '
        f'noise on'
    )

    # 1. whole closed loop: sit -> stand -> balance
    for name, beta in (('true beta', tb), ('2.5 cm wrong beta', wrong)):
        wall = best(lambda: run_balance(robot, tb, beta, seconds=args.seconds), args.repeat)
        print(
            f'run_balance {args.seconds:.0f} s, {name:18s}: {wall:6.3f} s wall = '
            f'{args.seconds / wall:6.1f}x real '
            f'time (target 100x: {args.seconds / wall / 100:.2f} of it)'
        )

    # 2. steady balancing only
    loop = ClosedLoop(robot, tb, tb, TABLE2_POSE, controller_config=cfg, log_rate_hz=30.0)
    loop.run(0.5)
    loop.controller.set_enabled(True)
    loop.run(10.0)
    wall = best(lambda: loop.run(20.0), args.repeat)
    print(
        f'balancing only (20 s):                 {wall:6.3f} s wall = {20.0 / wall:6.1f}x real '
        f'time'
    )

    # 3. while the joints move (simulator re-reduces every 20 ms, controller tracks the pose)
    loop2 = ClosedLoop(robot, tb, tb, TABLE2_POSE, controller_config=cfg, log_rate_hz=0)
    loop2.run(0.5)
    loop2.controller.set_enabled(True)
    loop2.run(10.0)
    target = TABLE2_POSE.copy()
    target[0] -= 1.0
    loop2.sim.command_joints(target)
    t0 = time.perf_counter()
    loop2.run(2.0)
    wall = time.perf_counter() - t0
    print(
        f'joints moving (2 s, waist at 0.44 rad/s):  {wall:6.3f} s wall = {2.0 / wall:6.1f}x real '
        f'time'
    )

    # 4. per-step costs
    n = 20000
    ctl = loop.controller
    samples = [loop.control_sample() for _ in range(n)]
    t_start = samples[-1].t
    for k, s in enumerate(samples):
        s.t = t_start + (k + 1) * ctl.h

    def run_ctl(c, ss):
        step = c.step
        for s in ss:
            step(s)

    wall = best(lambda: run_ctl(ctl, samples), args.repeat)
    fast_us = wall / n * 1e6
    mode = ctl.mode.value
    print(
        f'BalanceController.step ({mode}): {fast_us:6.2f} us/step = '
        f'{fast_us / period_us:.4f} of the period'
    )
    ad = ctl.adrc

    def run_adrc():
        for k in range(n):
            ad.update(0.001, 0.01, ctl.h, dtheta=0.0, dx=0.0)

    w = best(run_adrc, args.repeat)
    print(f'  ADRC law alone (AdrcController.update): {w / n * 1e6:6.2f} us')

    plant = ReducedPlant(robot, tb, TABLE2_POSE)
    plant.step()  # at rest where reduced: the hot path from here
    sensors = SensorModel(robot)
    m = 20000
    w_fast = best(lambda: [plant.step(2) for _ in range(m)], args.repeat)

    def full_steps():
        for _ in range(m):
            plant._step_one()
            plant._step_one()

    w_ref = best(full_steps, 1)
    print(
        f'  physics, 2 steps per control period: ReducedPlant.step {w_fast / m * 1e6:6.2f} us, '
        f'the full step {w_ref / m * 1e6:6.2f} us ({w_ref / w_fast:.1f}x)'
    )
    w_s = best(lambda: [sensors.control_sample(plant) for _ in range(m)], args.repeat)
    w_r = best(lambda: [sensors.sample(plant.motion()) for _ in range(m)], 1)
    print(
        f'  sensors: SensorModel.control_sample {w_s / m * 1e6:6.2f} us, every device (sample of '
        f'motion) {w_r / m * 1e6:6.2f} us ({w_r / w_s:.1f}x)'
    )
    # redesign on a pose or beta change
    k0 = time.perf_counter()
    for k in range(20):
        p = TABLE2_POSE.copy()
        p[0] -= 0.01 * (k + 1)
        ctl._redesign(p)
    print(
        f'  pose/beta change (reduce_pose + LQR(q)): {(time.perf_counter() - k0) / 20 * 1e3:6.2f} '
        f'ms each'
    )
    k0 = time.perf_counter()
    for k in range(50):
        ctl._offset_for(TABLE2_POSE)
    print(
        f'  CoM-offset refresh while joints move: {(time.perf_counter() - k0) / 50 * 1e3:6.2f} ms '
        f'each'
    )


if __name__ == '__main__':
    main()
