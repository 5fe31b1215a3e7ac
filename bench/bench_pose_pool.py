"""Safe balanced pose pool throughput (the authors' C++ generator: ~20,000 poses in about 2
minutes).

.venv/bin/python bench/bench_pose_pool.py [--n 20000]
"""

import argparse
import os
import time

import numpy as np

from krang_model.robot import load_krang
from krang_pose_server.pool import PosePool


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--n', type=int, default=20000)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args()
    print(f'load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores')
    robot = load_krang()
    pool = PosePool(robot)
    t0 = time.perf_counter()
    res = pool.generate(args.n, seed=args.seed)
    dt = time.perf_counter() - t0
    print(
        f'{args.n} poses in {dt:.2f} s: {args.n / dt:.0f} poses/s; {res.tries} tries '
        f'({res.tries / args.n:.2f} per pose; rejected {res.rejected})'
    )
    # where the time goes
    joints = np.random.default_rng(1).uniform(pool.lower, pool.upper, size=(20000, 16))
    t0 = time.perf_counter()
    q, ok = pool.balanced_candidates(joints)
    t_bal = time.perf_counter() - t0
    t0 = time.perf_counter()
    for qb, jt in zip(q[ok][:5000], joints[ok][:5000]):
        pool.checker.is_free(qb, jt)
    t_col = (time.perf_counter() - t0) / min(5000, int(ok.sum()))
    print(
        f'balance pitch + floor limits (vectorised): {1e6 * t_bal / len(joints):.1f} us/sample; '
        f'collision check (pinocchio/coal, {pool.checker.n_self_pairs} self pairs + floor): '
        f'{1e6 * t_col:.1f} us/candidate'
    )
    print(f"vs the authors' ~2 min for 20,000: {120 / dt * args.n / 20000:.0f}x faster")


if __name__ == '__main__':
    main()
