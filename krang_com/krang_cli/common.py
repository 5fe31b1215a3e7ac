"""Small helpers shared by the subcommands."""

import json
from pathlib import Path

from krang_sim.session_config import rate_overrides, sim_rate_hz


def print_json(payload):
    """Machine-readable result: always the last line of stdout."""
    print(json.dumps(payload, sort_keys=False))


def add_plant_argument(p, note=''):
    """--plant: the simulated robot's physics (None when not given: the reduced model)."""
    p.add_argument(
        '--plant',
        choices=('reduced', 'mujoco'),
        default=None,
        help="the simulated robot's physics: the controller's reduced model or the full-body "
        "MuJoCo Krang (sim_krang's `plant`; default the reduced model)" + note,
    )


def add_sim_robot_arguments(p, note=''):
    """--plant, --plant-model and --effects: the simulated robot, as sim_krang's parameters
    `plant`, `plant_model` and `effects` (`krang demo`, `krang bringup --sim`, the experiments)."""
    add_plant_argument(p, note)
    p.add_argument(
        '--plant-model',
        metavar='EXTENDED_MODEL.yaml',
        default=None,
        help='the simulated robot is the one an extended model of `krang discrepancy` describes '
        "(its effects and values; sim_krang's `plant_model`)" + note,
    )
    p.add_argument(
        '--effects',
        nargs='+',
        metavar='KEY=VALUE',
        default=None,
        help="the true robot's effects (krang_model.effects), on top of --plant-model, e.g. "
        'torque_constant=0.75 wheel_coulomb_friction=4 wheel_viscous_friction=3' + note,
    )


def sim_robot_overrides(args, robot):
    """sim_krang's parameters from --plant, --plant-model and --effects (those given). A bad
    extended model or effect raises ValueError here, in one line, before any node starts."""
    from krang_sim.plant import plant_terms

    try:
        plant_terms(robot, args.effects or (), args.plant_model)
    except (KeyError, ValueError, OSError) as err:
        raise ValueError(f'--plant-model / --effects: {err}') from None
    overrides = {}
    if args.plant:
        overrides['plant'] = args.plant
    if args.plant_model:
        overrides['plant_model'] = str(Path(args.plant_model).resolve())
    if args.effects:
        overrides['effects'] = list(args.effects)
    return overrides


def add_rate_argument(p, note=''):
    """--rate-hz: the simulated node set's sample and control rate (`krang demo`, `krang bringup
    --sim`)."""
    p.add_argument(
        '--rate-hz',
        type=float,
        default=None,
        metavar='HZ',
        help='sample and control rate of the simulated robot and its controller, Hz (default: '
        f"config/sim_params.yaml, {sim_rate_hz():g} Hz). 500 is the robot's rate and costs wall "
        'time: composed (`krang demo`) the node set runs at about 1x real time there and a demo '
        'takes about 2.5x as long as at 100 Hz; as processes on 2 cores it falls to about 0.5x '
        'real time. The physics rate (1000 Hz) must be a whole multiple of it' + note,
    )


def with_rate(overrides, rate_hz):
    """`overrides` (node -> {param: value}) with the parameters of `rate_hz`
    (krang_sim.session_config.rate_overrides; None: unchanged); ValueError for a bad rate."""
    merged = dict(overrides)
    for node, params in rate_overrides(rate_hz).items():
        merged[node] = {**merged.get(node, {}), **params}
    return merged
