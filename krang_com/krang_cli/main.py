"""`krang`: the user-facing command line. Each subcommand lives in its own module with
`register()`."""

import argparse
import importlib
import logging
import os
import sys

# Before numpy is imported, as in krang_ros/entry.py (the nodes): single-threaded OpenBLAS, which
# is faster for our small matrices and keeps the offline closed loop from stalling under load.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

# Order here is the order in `krang --help`.
COMMAND_MODULES = (
    'demo',
    'bringup',
    'evaluate',
    'learn',
    'relearn',
    'identifiability',
    'poses',
    'metrics',
    'experiment',
    'discrepancy',
    'bag',
    'view',
)


def build_parser():
    parser = argparse.ArgumentParser(
        prog='krang',
        description='Golem Krang online CoM estimation: evaluate and learn mass models, build and '
        'filter '
        'pose sets, run the simulated robot end to end, compute balancing metrics, find '
        'sim-vs-real discrepancies, and work with MCAP bags.',
        epilog='Run `krang <command> --help` for the options of each command.',
    )
    parser.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    subparsers = parser.add_subparsers(dest='command', metavar='<command>')
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(f'krang_cli.{name}')
        except ModuleNotFoundError as err:
            if err.name == f'krang_cli.{name}':
                continue  # not part of this install
            raise
        module.register(subparsers)
    return parser


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format='%(asctime)s %(levelname)s %(name)s: %(message)s',
        stream=sys.stderr,
    )
    if not getattr(args, 'func', None):
        parser.print_help()
        return 2
    try:
        return args.func(args) or 0
    except (
        ValueError,
        FileNotFoundError,
    ) as err:  # bad input files: a clear message, no traceback
        print(f'krang {args.command}: error: {err}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
