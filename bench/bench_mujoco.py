"""Real-time factor of the full-body MuJoCo plant at 1 kHz physics (goal >= 20x real time), and
how far the reduced model's one-step predictions are from it during pose moves.

    .venv/bin/python bench/bench_mujoco.py [--seconds 5] [--repeats 3]
    .venv/bin/python bench/bench_mujoco.py --one-step [--moves 3]

Each case simulates `--seconds` of the robot sitting on its caster in the Table II pose under the
hidden truth of the simulator (config/sim_true_beta.yaml), best of `--repeats`:

- reference: ``mujoco.mj_step`` on the plant's own compiled model, 1000 steps per call: the
  engine alone, no Python between steps. Measured in the same run, it is the yardstick: the
  ratio of each case to it says what the plant's Python costs, whatever else loads the machine.
- plant at 1 kHz: ``step(1)`` and ``wheel_pitch()`` every step (the offline loop's hot path at
  a 1 kHz control rate);
- plant at 500 Hz: ``step(2)`` and ``motion()`` every 2 ms (the robot's control rate);
- arms moving: as at 500 Hz while the waist and both shoulders move (the modules' setpoints
  advance every 4 ms).

``--one-step``: the robot stands up and balances under the ADRC controller on the MuJoCo plant,
then moves to `--moves` poses of the pose pool as the pose server streams them (`--stream-hz`;
0 sends each goal at once). Every control
period (2 ms) the reduced model (``krang_model.wip``: the pose as it is, locked, reduced to one
body on the axle, under the same wheel torques) predicts the next state from MuJoCo's; the
report is the error of its pitch and wheel accelerations while the arms move and while they rest.
"""

import argparse
import time

import mujoco
import numpy as np

from krang_model.beta import load_beta
from krang_model.config import config_path
from krang_model.robot import load_krang
from krang_sim.plant import make_plant

TABLE2_POSE = np.array(
    [2.75467, 0.0749392, 1.00799, -1.113, -0.000251086, -1.59399, 0.0370958, 1.02202]
    + [-0.0209895, -0.854931, 1.113, 0.000271173, 1.561, -0.0280979, -1.052, 0.0210068]
)


def _plant():
    robot = load_krang()
    return make_plant(
        'mujoco', robot, load_beta(config_path('sim_true_beta.yaml'), robot), TABLE2_POSE
    )


def reference(seconds):
    p = _plant()
    n = int(seconds / p.dt)
    t0 = time.perf_counter()
    for _ in range(n // 1000):
        mujoco.mj_step(p.model, p.data, nstep=1000)
    return time.perf_counter() - t0


def at_1khz(seconds):
    p = _plant()
    t0 = time.perf_counter()
    for _ in range(int(seconds / p.dt)):
        p.step(1)
        p.wheel_pitch()
    return time.perf_counter() - t0


def at_500hz(seconds, move=False):
    p = _plant()
    if move:
        target = TABLE2_POSE.copy()
        target[0] -= 0.4
        target[3] += 0.6
        target[10] -= 0.6
        p.command_joints(target)
    t0 = time.perf_counter()
    for k in range(int(seconds / (2 * p.dt))):
        if move and k % 1000 == 999:  # keep them moving: back and forth every 2 s
            p.command_joints(TABLE2_POSE if k // 1000 % 2 else target)
        p.step(2)
        p.motion()
    return time.perf_counter() - t0


def one_step(n_moves, stream_hz):
    from krang_model.drivetrain import drivetrain
    from krang_model.wip import WipDynamics, reduce_pose
    from krang_pose_server.pool import generate_pool
    from krang_sim.closed_loop import ClosedLoop

    robot = load_krang()
    truth = load_beta(config_path('sim_true_beta.yaml'), robot)
    loop = ClosedLoop(robot, truth, truth, TABLE2_POSE, plant='mujoco')
    plant, drive = loop.plant, drivetrain(robot)
    k = drive.torque_constant * drive.gear_ratio
    # arms moving -> [(pitch, wheel) acceleration errors, (pitch, wheel) accelerations]
    errors = {True: [], False: []}
    last = {}

    def hook(t, sample, out, currents):
        """Compare the reduced model's prediction from the previous period with MuJoCo's."""
        state = list(plant.truth().state)
        if last and last['mode'] == 'balance':
            dyn = WipDynamics(reduce_pose(robot, last['joints'], plant.true_beta), drive)
            pred = last['state']
            for _ in range(loop.n_sub):
                pred = dyn.step(pred, *last['torques'], plant.dt)
            h = loop.n_sub * plant.dt
            was = last['state']
            errors[last['moving']].append(
                (
                    (state[3] - pred[3]) / h,
                    (state[2] - pred[2]) / h,
                    (state[3] - was[3]) / h,
                    (state[2] - was[2]) / h,
                )
            )
        last.update(
            state=state,
            torques=tuple(k * i for i in currents),
            joints=plant.joints,
            moving=plant.joints_moving,
            mode=out.mode,
        )
        return currents

    loop.run(1.0)
    loop.controller.set_enabled(True)
    loop.run(9.0)
    loop.command_hook = hook
    loop.run(2.0)  # at rest
    poses = generate_pool(n_moves, seed=1, real_beta=truth).joints
    for goal in poses:
        loop.start_move(goal, rate_hz=stream_hz)
        loop.run(40.0, until=lambda o: loop.streamer is None and not plant.joints_moving)
        loop.run(2.0)
    print(
        f'mode at the end: {loop.controller.mode.value}; {n_moves} moves streamed at '
        f'{stream_hz:g} Hz (0: the goal at once)'
    )
    print('reduced model against MuJoCo, one control period ahead (rad/s^2):')
    for moving, label in ((False, 'arms at rest'), (True, 'arms moving')):
        e = np.abs(np.array(errors[moving]))
        if not len(e):
            print(f'  {label}: no samples')
            continue
        rms = np.sqrt(np.mean(e**2, axis=0))
        print(
            f'  {label:13s} {len(e):6d} periods  pitch acc. error rms {rms[0]:.3f} max '
            f'{e[:, 0].max():.3f} (the acc. itself: rms {rms[2]:.3f}); wheel acc. error rms '
            f'{rms[1]:.3f} max {e[:, 1].max():.3f} (rms {rms[3]:.3f})'
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=5.0, help='simulated s per case')
    parser.add_argument('--repeats', type=int, default=3, help='best of')
    parser.add_argument('--one-step', action='store_true', help='the one-step comparison')
    parser.add_argument('--moves', type=int, default=3, help='pose moves of --one-step')
    parser.add_argument(
        '--stream-hz', type=float, default=20.0, help="the pose server's setpoint rate (0: none)"
    )
    args = parser.parse_args()
    if args.one_step:
        one_step(args.moves, args.stream_hz)
        return
    s = args.seconds
    cases = {
        'reference (mj_step x1000)': lambda: reference(s),
        'plant at 1 kHz (step(1) + wheel_pitch)': lambda: at_1khz(s),
        'plant at 500 Hz (step(2) + motion)': lambda: at_500hz(s),
        'arms moving, 500 Hz': lambda: at_500hz(s, move=True),
    }
    print(f'mujoco {mujoco.__version__}, 1 kHz physics, {s:.0f} simulated s per case')
    ref = None
    for name, run in cases.items():
        wall = min(run() for _ in range(args.repeats))
        ref = wall if ref is None else ref
        print(
            f'{name:42s} {s / wall:6.1f}x real time  ({1e6 * wall / (s * 1000):5.1f} us/step, '
            f'{wall / ref:4.2f}x the reference)'
        )
    print('goal: >= 20x real time at 1 kHz physics')


if __name__ == '__main__':
    main()
