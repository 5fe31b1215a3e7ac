"""Algorithm 1 (pose filtering) at the paper's scale: 22,000 poses x 500 betas x 92 parameters.

Times our implementation (betas updated by rank-one steps, rows evaluated exactly only where the
bound says they can still win) against the straightforward one (Phi^T beta_k recomputed for the
whole pool every iteration) and asserts identical selections.

    .venv/bin/python bench/bench_pose_filter.py            # straightforward on the first 100
    iterations,
                                                           # extrapolated to the full run (said so)
    .venv/bin/python bench/bench_pose_filter.py --full     # straightforward to the end (a few
    minutes)
"""

import argparse
import os
import time

import numpy as np

from krang_model.com import phi
from krang_model.robot import load_krang
from krang_pose_server.erroneous_betas import authors_betas
from krang_pose_server.filtering import filter_poses, filter_straightforward
from krang_pose_server.pool import PosePool


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--pool', type=int, default=22000)
    ap.add_argument('--betas', type=int, default=500)
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument(
        '--slice',
        type=int,
        default=100,
        help='iterations of the straightforward run (default 100)',
    )
    ap.add_argument(
        '--full', action='store_true', help='run the straightforward algorithm to the end'
    )
    args = ap.parse_args()
    robot = load_krang()
    print(f'load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores')
    t0 = time.perf_counter()
    pool = PosePool(robot).generate(args.pool, seed=args.seed)
    Phi = phi(robot, pool.q_base, pool.joints)
    betas = authors_betas(
        robot.nominal_beta, args.betas, np.random.default_rng(args.seed + 1), first_phi=Phi[0]
    )
    print(
        f'problem: {Phi.shape[0]} poses x {betas.shape[0]} betas x {Phi.shape[1]} parameters '
        f'(pool built in {time.perf_counter() - t0:.1f} s)'
    )

    c0 = time.process_time()
    fast = filter_poses(Phi, betas, 'paper-l1')
    cpu_fast = time.process_time() - c0
    n = len(fast.selected)
    print(
        f'ours:            {n} poses selected (converged={fast.converged}) in {fast.seconds:.2f} '
        f's wall, '
        f'{cpu_fast:.2f} s CPU ({1e3 * fast.seconds / n:.2f} ms/iteration; '
        f'{fast.evaluations / n:.0f} exact rows '
        f'per iteration of {args.pool})'
    )

    limit = None if args.full else min(args.slice, n)
    c0 = time.process_time()
    ref = filter_straightforward(Phi, betas, 'paper-l1', max_poses=limit)
    cpu_ref = time.process_time() - c0
    m = len(ref.selected)
    same = np.array_equal(ref.selected, fast.selected[:m])
    assert same, 'selections differ'
    per_it = ref.seconds / m
    if args.full:
        assert m == n and ref.converged
        print(
            f'straightforward: {m} poses in {ref.seconds:.1f} s wall, {cpu_ref:.1f} s CPU '
            f'({1e3 * per_it:.1f} ms/iteration); identical selections: {same}'
        )
        total, total_cpu = ref.seconds, cpu_ref
    else:
        total, total_cpu = per_it * n, cpu_ref / m * n
        print(
            f'straightforward: first {m} iterations in {ref.seconds:.1f} s wall, {cpu_ref:.1f} s '
            f'CPU '
            f'({1e3 * per_it:.1f} ms/iteration); identical selections on those {m}: {same}'
        )
        print(
            f'                 EXTRAPOLATED to {n} iterations: {total:.0f} s wall, '
            f'{total_cpu:.0f} s CPU '
            f'(run with --full to measure)'
        )
    print(f'speed-up: {total / fast.seconds:.0f}x wall, {total_cpu / cpu_fast:.0f}x CPU')


if __name__ == '__main__':
    main()
