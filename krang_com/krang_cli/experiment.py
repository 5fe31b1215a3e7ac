"""krang experiment: the paper's experiments in closed-loop simulation.

The experiments live in the krang_experiments package (one module each: `run(params) -> result`,
`report(result, out_dir)`); this module only turns the command line into their Params.
Sub-subcommands are registered in ``EXPERIMENTS``; adding one is a small function pair::

    from krang_cli.experiment import register_experiment
    def _args(p): p.add_argument('--out', default='out/mine')
    def _run(args): ...; return 0
    register_experiment('mine', 'one-line help', _args, _run)

Modules named ``krang_cli/experiment_*.py`` are imported when the parser is built, so another
engineer's file can register its experiments this way without touching this one; such a module may
instead define ``register_experiment(experiment_subparsers)`` and add its own sub-subparser (as
``experiment_learning.py`` does for ``krang experiment learning``).

Built in:
* ``table2``: Table II in simulation (krang_experiments.table2).
* ``adrc-vs-lqr``: ADRC and plain LQR with the same wrong CoM (krang_experiments.adrc_vs_lqr).
* ``many-truths``: the online session on many hidden truths (krang_experiments.many_truths).
* ``campaign``: the online session across plants and drive chains (krang_experiments.campaign).

``table2``, ``many-truths`` and ``campaign`` take the simulated robot's physics (``--plant``) and
an extended model of `krang discrepancy` (``--plant-model``).

The experiment modules are imported when a command runs, not at parser time: they load the
simulator and matplotlib, which every other `krang` command would otherwise pay for.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import krang_cli

from .common import add_plant_argument, add_sim_robot_arguments, print_json

# ----------------------------------------------------------------------------- registry


@dataclass
class Experiment:
    name: str
    help: str
    add_arguments: Callable
    run: Callable
    description: str | None = None


EXPERIMENTS: dict[str, Experiment] = {}


def register_experiment(name, help, add_arguments, run, description=None):
    """Add `krang experiment NAME`: add_arguments(parser) declares options, run(args) -> exit
    code."""
    EXPERIMENTS[name] = Experiment(name, help, add_arguments, run, description)


def _discover():
    """Import krang_cli/experiment_*.py (they may call register_experiment at import) and return
    them."""
    found = []
    for mod in sorted(pkgutil.iter_modules(krang_cli.__path__), key=lambda m: m.name):
        if mod.name.startswith('experiment_'):
            try:
                found.append(importlib.import_module(f'krang_cli.{mod.name}'))
            except Exception as err:  # one broken plug-in must not take `krang experiment` down
                print(f'krang experiment: skipped krang_cli.{mod.name} ({err})', file=sys.stderr)
    return found


def register(subparsers):
    p = subparsers.add_parser(
        'experiment',
        help="the paper's experiments in closed-loop simulation",
        description=__doc__.split('\n\n')[0] + ' Run `krang experiment <name> --help`.',
    )
    sub = p.add_subparsers(dest='experiment', metavar='<experiment>')
    plugins = _discover()
    for exp in EXPERIMENTS.values():
        sp = sub.add_parser(
            exp.name,
            help=exp.help,
            description=exp.description or exp.help,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        exp.add_arguments(sp)
        sp.set_defaults(func=exp.run)
    # second protocol: a module-level hook `register_experiment(experiment_subparsers)` that adds
    # its own sub-subparsers (e.g. krang_cli/experiment_learning.py -> `krang experiment learning`)
    for mod in plugins:
        hook = getattr(mod, 'register_experiment', None)
        if callable(hook) and hook is not register_experiment:
            hook(sub)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


# ----------------------------------------------------------------------------- adrc-vs-lqr


def _adrc_args(p):
    p.add_argument('--out', default='out/adrc_vs_lqr', help='output folder (report.md, PNG, JSON)')
    p.add_argument(
        '--shift',
        type=float,
        default=0.025,
        help='CoM error of the wrong beta in m (default 0.025)',
    )
    p.add_argument('--seed', type=int, default=5)
    p.add_argument(
        '--true-beta', default=None, help='hidden truth (default config/sim_true_beta.yaml)'
    )
    p.add_argument(
        '--params', default=None, help='controller YAML (default config/controller.yaml)'
    )
    p.add_argument(
        '--json', action='store_true', help='print a JSON summary as the last stdout line'
    )


def _run_adrc(args):
    from krang_experiments import adrc_vs_lqr

    result = adrc_vs_lqr.run(
        adrc_vs_lqr.Params(
            shift=args.shift, seed=args.seed, true_beta=args.true_beta, params=args.params
        )
    )
    print(adrc_vs_lqr.report(result, args.out))
    if args.json:
        print_json({'out': str(Path(args.out)), 'variants': result['summary']})
    return 0


register_experiment(
    'adrc-vs-lqr',
    'ADRC vs plain LQR with the same wrong CoM (stand-up, push, pose change)',
    _adrc_args,
    _run_adrc,
)


# ----------------------------------------------------------------------------- table2


def _table2_args(p):
    p.add_argument(
        '--out', default='out/table2', help='output folder (report.md, PNGs, JSON, learned betas)'
    )
    p.add_argument(
        '--runs',
        type=int,
        default=7,
        help='stand-up-and-balance runs per beta (noise seeds 0..runs-1)',
    )
    p.add_argument(
        '--poses',
        type=int,
        default=189,
        help="poses to learn from (default 189: beta_190 = row 189, the paper's numbering)",
    )
    p.add_argument(
        '--order',
        choices=('authors', 'file'),
        default='authors',
        help="pose order: the authors' hardware training order of the filtered poses (kit "
        'hardware_balanced_poses_train.csv) or the file order of finalSetMunzir.txt',
    )
    p.add_argument('--seconds', type=float, default=62.0, help='length of each balancing run (s)')
    p.add_argument(
        '--kit',
        default=None,
        help='real-data kit folder (default $KRANG_DATA or shared/krang_data beside the checkout)',
    )
    p.add_argument(
        '--true-beta', default=None, help='hidden truth (default config/sim_true_beta.yaml)'
    )
    p.add_argument(
        '--params', default=None, help='controller YAML (default config/controller.yaml)'
    )
    p.add_argument('--seed', type=int, default=0, help='seed of the learning session')
    p.add_argument(
        '--betas',
        default=None,
        metavar='FILE',
        help='skip the learning: take the betas (row k = after k updates) from FILE, e.g. the '
        'learned_betas.txt of an earlier run',
    )
    p.add_argument(
        '--paper-era-pd',
        action='store_true',
        help="the 2018 runs' controller instead of ours: the paper-era stand PD (250, 40, 4, 10) "
        'for the whole run (on the hardware the switch to balance needed |theta| < 0.034 rad, '
        'which the learned betas never met), no ADRC',
    )
    p.add_argument(
        '--plant-model',
        '--extended-model',
        dest='plant_model',
        default=None,
        metavar='EXTENDED_MODEL.yaml',
        help='simulate the robot with the effects `krang discrepancy` found (its '
        'extended_model.yaml, e.g. from the hardware Table II runs), to compare the simulated '
        'table with the hardware',
    )
    add_plant_argument(p)
    p.add_argument(
        '--json', action='store_true', help='print the table as JSON on the last stdout line'
    )


def _run_table2(args):
    from krang_experiments import table2

    params = table2.Params(
        runs=args.runs,
        poses=args.poses,
        order=args.order,
        seconds=args.seconds,
        kit=args.kit,
        true_beta=args.true_beta,
        params=args.params,
        seed=args.seed,
        betas=args.betas,
        paper_era_pd=args.paper_era_pd,
        extended_model=args.plant_model,
        plant=args.plant or 'reduced',
    )
    result = table2.run(params)
    print(table2.report(result, args.out))
    if args.json:
        print_json(result['summary'])
    return 0


register_experiment(
    'table2',
    'Table II in simulation: learn online, then 7 stand-up-and-balance runs per beta',
    _table2_args,
    _run_table2,
)


# ----------------------------------------------------------------------------- many-truths


def _many_truths_args(p):
    p.add_argument('--out', default='out/many_truths', help='output folder (PNG, JSON)')
    p.add_argument('--truths', type=int, default=10, help='number of hidden truths (default 10)')
    p.add_argument(
        '--first-seed',
        type=int,
        default=5000,
        help='truth seeds first-seed, first-seed + 1, ... (default 5000)',
    )
    p.add_argument('--poses', type=int, default=12, help='poses per session (default 12)')
    p.add_argument(
        '--selection',
        choices=('fixed', 'adaptive', 'both'),
        default='both',
        help='pose selection: the meta-learned list, adaptive, or both (default)',
    )
    p.add_argument('--method', default='map-online', help='estimator (default map-online)')
    add_sim_robot_arguments(p)
    p.add_argument(
        '--json', action='store_true', help='print a JSON summary as the last stdout line'
    )


def _run_many_truths(args):
    from krang_experiments import many_truths

    selections = many_truths.SELECTIONS if args.selection == 'both' else (args.selection,)
    params = many_truths.Params(
        truth_seeds=tuple(range(args.first_seed, args.first_seed + args.truths)),
        n_poses=args.poses,
        selections=selections,
        method=args.method,
        progress=True,
        plant=args.plant or 'reduced',
        plant_model=args.plant_model,
        effects=tuple(args.effects or ()),
    )
    result = many_truths.run(params)
    print(many_truths.report(result, args.out))
    if args.json:
        print_json({'out': str(Path(args.out)), 'summary': result['summary']})
    return 0


register_experiment(
    'many-truths',
    'the online session on many hidden truths: fixed pose list vs adaptive selection',
    _many_truths_args,
    _run_many_truths,
)


# ----------------------------------------------------------------------------- campaign


def _campaign_args(p):
    p.add_argument('--out', default='out/campaign', help='output folder (PNG, JSON, Markdown)')
    p.add_argument('--truths', type=int, default=10, help='number of hidden truths (default 10)')
    p.add_argument('--first-seed', type=int, default=5000, help='first truth seed (default 5000)')
    p.add_argument('--poses', type=int, default=12, help='poses per session (default 12)')
    p.add_argument(
        '--plants', nargs='+', default=['reduced', 'mujoco'], choices=('reduced', 'mujoco')
    )
    p.add_argument(
        '--chains',
        nargs='+',
        default=['nominal', 'gearmotor'],
        help='drive chains of krang_experiments.campaign.CHAINS (nominal, gearmotor, '
        'gear-light, gear-hard; default nominal gearmotor)',
    )
    p.add_argument(
        '--chain-unknown',
        action='store_true',
        help='run the shipped controller configuration instead of telling it the drive chain',
    )
    p.add_argument(
        '--plant-model',
        default=None,
        metavar='EXTENDED_MODEL.yaml',
        help='an extended model of `krang discrepancy` under every chain',
    )
    p.add_argument(
        '--move-points',
        type=int,
        default=None,
        metavar='N',
        help='points the controller reads on each move (its move_points.per_move; default: the '
        "shipped configuration's)",
    )
    p.add_argument(
        '--short', action='store_true', help="the default test run's version (about 30 s)"
    )
    p.add_argument(
        '--json', action='store_true', help='print a JSON summary as the last stdout line'
    )


def _run_campaign(args):
    from krang_experiments import campaign

    params = campaign.Params(
        truth_seeds=tuple(range(args.first_seed, args.first_seed + args.truths)),
        plants=tuple(args.plants),
        chains=tuple(args.chains),
        n_poses=args.poses,
        chain_known=not args.chain_unknown,
        plant_model=args.plant_model,
        progress=True,
        controller={} if args.move_points is None else {'move_points.per_move': args.move_points},
    )
    if args.short:
        params = campaign.short(params)
    result = campaign.run(params)
    command = 'krang experiment campaign ' + ' '.join(sys.argv[3:])
    print(campaign.report(result, args.out, command=command))
    if args.json:
        print_json({'out': str(Path(args.out)), 'summary': result['summary']})
    return 0


register_experiment(
    'campaign',
    'the online session across plants (reduced, MuJoCo) and drive chains (nominal, gearmotors)',
    _campaign_args,
    _run_campaign,
)
