"""Run the benchmarks and write docs/performance.md: one section per benchmark, each a table with
the command that produced it.

    .venv/bin/python bench/report.py [--only NAME ...] [--runs N] [--out FILE]
    .venv/bin/python bench/report.py --list | --check

Each section of the file sits between ``<!-- bench: NAME -->`` and ``<!-- /bench: NAME -->``. A run
rewrites the sections it reruns (every one, or those named by --only) and keeps the text of every
other section, and everything outside the markers, as it is: one benchmark can be rerun alone. A
benchmark that fails, or whose output cannot be read, leaves its section as it was, and the report
ends with exit code 1 naming it. --check only reads the file and says whether every section is
there (no benchmark runs). A section with plants runs its benchmark once per simulated plant
(`--plant P`) and sets the figures of the plants side by side.

Figures come from a benchmark's JSON line (``--json``) where it has one. Where it has none yet,
they come from the lines it prints, read by a pattern per figure (the ``read_*`` functions below);
a pattern that does not match the output is an error, never a silently missing figure. The
sections run one after the other, so no two benchmarks share the machine.
"""

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / 'docs' / 'performance.md'
PY = '.venv/bin/python'  # how the commands are written in the document
BLOCK = re.compile(r'<!-- bench: (\S+) -->\n(.*?)<!-- /bench: \1 -->\n?', re.S)

HEADER = """# Performance

Every table below is written by `bench/report.py`, which runs the benchmark named under its heading
and puts the figures in the table; `bench/report.py --only NAME` reruns one section and keeps the
others. Timings are wall-clock on the machine that ran the report: rerun them where it matters
(the robot computer for the control path). Ranges are the lowest and highest of the runs a section
makes.

"""


class ReportError(RuntimeError):
    """A benchmark that failed or printed something this report cannot read."""


@dataclass
class Section:
    """One benchmark's section. `argv` runs from the repository root ('PY': this interpreter,
    'KRANG': the krang command, 'OUT': a temporary directory); `read` turns one run's stdout into
    a figures dict, `table` the figures of all runs into markdown lines. With `plants`, the
    benchmark runs once per plant with `--plant P` added, and `table` gets {plant: runs}."""

    name: str
    title: str
    argv: list
    read: Callable[[str], dict]
    table: Callable[[list], list]
    about: str = ''
    runs: int = 1
    json_mode: bool = False  # the benchmark prints its figures as JSON
    env: dict = field(default_factory=dict)
    plants: tuple = ()  # sim_krang's `plant` values to run the benchmark on, side by side

    def command(self):
        """The command as the document shows it."""
        words = {'PY': PY, 'KRANG': 'krang', 'OUT': 'DIR'}
        plant = ['--plant', 'P'] if self.plants else []
        return ' '.join(words.get(a, a) for a in self.argv + plant)

    def argv_to_run(self, out_dir, plant=None):
        words = {'PY': [sys.executable], 'KRANG': [sys.executable, '-m', 'krang_cli.main']}
        words['OUT'] = [str(out_dir)]
        plant = ['--plant', plant] if plant else []
        return [w for a in self.argv for w in words.get(a, [a])] + plant


# ---- reading a benchmark's output ------------------------------------------------------------
def last_json(out):
    """The JSON object on the last line that holds one."""
    for line in reversed(out.strip().splitlines()):
        line = line.strip()
        if line.startswith('{'):
            return json.loads(line)
    raise ReportError('no JSON line in the output')


def grab(pattern, out, *, cast=float, group=1):
    """One figure printed by a benchmark without --json: the first group of `pattern`."""
    m = re.search(pattern, out, re.M)
    if m is None:
        raise ReportError(f'the output has no line matching {pattern!r}')
    value = m.group(group)
    return cast(value.replace(',', '')) if cast is not str else value


def grab_all(pattern, out):
    found = re.findall(pattern, out, re.M)
    if not found:
        raise ReportError(f'the output has no line matching {pattern!r}')
    return found


def markdown_lines(out):
    """The markdown table a benchmark prints itself, and the summary line after it."""
    lines = [ln for ln in out.strip().splitlines() if not ln.startswith('WALL ')]
    table = [ln for ln in lines if ln.startswith('|')]
    if not table:
        raise ReportError('the output has no markdown table')
    after = lines[lines.index(table[-1]) + 1 :]
    return {'table': table, 'summary': [ln for ln in after if ln.strip()]}


# ---- formatting ---------------------------------------------------------------------------------
def span(values, fmt='{:.2f}', unit=''):
    """'a' for one value or equal values, 'lo–hi' for several."""
    values = [v for v in values if v is not None and not math.isnan(v)]
    if not values:
        return '–'
    lo, hi = min(values), max(values)
    text = (
        fmt.format(lo)
        if fmt.format(lo) == fmt.format(hi)
        else f'{fmt.format(lo)}–{fmt.format(hi)}'
    )
    return text + unit


def rows(header, body):
    out = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    return out + ['| ' + ' | '.join(str(c) for c in r) + ' |' for r in body]


def col(runs, key):
    return [r[key] for r in runs]


# ---- the sections -------------------------------------------------------------------------------
def read_phi(out):
    return {
        'batched': grab(r'phi batched .*?: ([\d,]+) poses/s', out),
        'per_pose': grab(r'pinocchio per pose .*?: ([\d,]+) poses/s', out),
    }


def table_phi(runs):
    b, p = col(runs, 'batched'), col(runs, 'per_pose')
    return rows(
        ['figure', 'value', 'target'],
        [
            [
                'phi(q) batched (numpy, 20,000-pose batches)',
                span(b, '{:,.0f}', ' poses/s'),
                '≥ 100,000 poses/s',
            ],
            ['pinocchio, one pose at a time', span(p, '{:,.0f}', ' poses/s'), ''],
            ['batched / per pose', span([x / y for x, y in zip(b, p)], '{:.0f}', '×'), ''],
        ],
    )


def read_wip(out):
    return {
        'euler': grab(r'real-time factor: (\d+)x', out),
        'rk4': grab(r'RK4 for comparison: (\d+)x', out),
    }


def table_wip(runs):
    return rows(
        ['integrator (1 kHz step, LQR in the loop)', 'real-time factor', 'target'],
        [
            [
                "semi-implicit Euler (the simulator's)",
                span(col(runs, 'euler'), '{:.0f}', '×'),
                '≥ 200×',
            ],
            ['RK4', span(col(runs, 'rk4'), '{:.0f}', '×'), ''],
        ],
    )


def read_pool(out):
    return {
        'n': grab(r'^(\d+) poses in ', out),
        'seconds': grab(r'^\d+ poses in ([\d.]+) s', out),
        'rate': grab(r' s: (\d+) poses/s', out),
    }


def table_pool(runs):
    return rows(
        ['safe balanced poses', 'wall time', 'poses/s', "the authors' C++"],
        [
            [
                span(col(runs, 'n'), '{:,.0f}'),
                span(col(runs, 'seconds'), '{:.1f}', ' s'),
                span(col(runs, 'rate'), '{:,.0f}'),
                'about 2 min for 20,000',
            ],
        ],
    )


def read_filter(out):
    return {
        'selected': grab(r'^ours:\s+(\d+) poses selected', out),
        'ours': grab(r'^ours:.* in ([\d.]+) s wall', out),
        'straight': grab(r'^straightforward: \d+ poses in ([\d.]+) s wall', out),
        'same': grab(r'identical selections: (\w+)', out, cast=str),
    }


def table_filter(runs):
    return rows(
        [
            'Algorithm 1, 22,000 poses × 500 betas × 92',
            'poses selected',
            'wall time',
            'identical selections',
        ],
        [
            [
                'ours (`krang_pose_server.filtering`)',
                span(col(runs, 'selected'), '{:.0f}'),
                span(col(runs, 'ours'), '{:.2f}', ' s'),
                '',
            ],
            [
                'the straightforward algorithm',
                '',
                span(col(runs, 'straight'), '{:.1f}', ' s'),
                ', '.join(sorted(set(col(runs, 'same')))),
            ],
            [
                'speed-up',
                '',
                span(
                    [s / o for s, o in zip(col(runs, 'straight'), col(runs, 'ours'))],
                    '{:.0f}',
                    '×',
                ),
                '',
            ],
        ],
    )


def read_closed_loop(out):
    x = r'([\d.]+)x real'
    return {
        'true': grab(r'^run_balance .*true beta\s*:.*= +' + x, out),
        'wrong': grab(r'^run_balance .*2\.5 cm wrong beta\s*:.*= +' + x, out),
        'balancing': grab(r'^balancing only .*= +' + x, out),
        'moving': grab(r'^joints moving .*= +' + x, out),
        'step_us': grab(r'^BalanceController\.step .*?: +([\d.]+) us/step', out),
        'adrc_us': grab(r'ADRC law alone .*?: +([\d.]+) us', out),
        'redesign_ms': grab(r'pose/beta change .*?: +([\d.]+) ms', out),
    }


def table_closed_loop(runs):
    def f(k, fmt, unit):
        return span(col(runs, k), fmt, unit)

    return rows(
        ['figure (controller at 500 Hz, physics at 1 kHz, sensor noise on)', 'value', 'target'],
        [
            ['sit → stand → balance, true beta', f('true', '{:.0f}', '× real time'), '≥ 100×'],
            ['sit → stand → balance, beta 2.5 cm wrong', f('wrong', '{:.0f}', '× real time'), ''],
            ['balancing only', f('balancing', '{:.0f}', '× real time'), ''],
            ['while the joints move', f('moving', '{:.0f}', '× real time'), ''],
            ['one controller step in BALANCE', f('step_us', '{:.1f}', ' µs'), '≪ 2 ms'],
            ['the ADRC law alone', f('adrc_us', '{:.2f}', ' µs'), ''],
            [
                'redesign on a pose or beta change (reduction + LQR(q))',
                f('redesign_ms', '{:.1f}', ' ms'),
                '',
            ],
        ],
    )


def read_discrepancy(out):
    result = json.loads(grab(r'^result: (\{.*\})$', out, cast=str))
    return {'seconds': grab(r'^full discrepancy run: ([\d.]+) s', out), **result}


def table_discrepancy(runs):
    r = runs[-1]
    return rows(
        ['60 s simulated record, hidden floor slope 0.02 rad', 'value'],
        [
            ['full `krang discrepancy` run', span(col(runs, 'seconds'), '{:.1f}', ' s')],
            ['named', f'{r.get("effect")} = {r.get("value", float("nan")):.4g}'],
            [
                'gap before → after',
                f'{r.get("gap_before", float("nan")):.3f} → '
                f'{r.get("gap_after", float("nan")):.3f}',
            ],
        ],
    )


def table_markdown(runs):
    r = runs[-1]
    return r['table'] + ([''] + r['summary'] if r['summary'] else [])


def read_imu_bias(out):
    found = grab_all(
        r'^\s*([\d.]+e[+-]\d+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)(\s+<-)?', out
    )
    return {'rows': [[*r[:6], bool(r[6])] for r in found]}


def table_imu_bias(runs):
    body = [[f'{r[0]}' + (' (configured)' if r[6] else ''), *r[1:6]] for r in runs[-1]['rows']]
    return rows(
        [
            'bias process noise',
            'tracking τ (s)',
            'error 90–120 s after a bias step, sitting (mrad)',
            'sitting peak (mrad)',
            'balancing peak (mrad)',
            'harsh motion, rms (mrad)',
        ],
        body,
    ) + [
        '',
        'Figure: [imu_bias_tradeoff.png](imu_bias_tradeoff.png), written by the same command.',
    ]


def read_latency(out):
    return last_json(out)


def table_latency(runs):
    def f(k, fmt='{:.2f}', unit=' ms', scale=1.0):
        return span([r[k] * scale for r in runs], fmt, unit)

    return rows(
        ['figure', 'ours (`can_bridge` + `adrc_controller`)', 'bare rclpy chain', 'ratio', 'goal'],
        [
            ['latency p50', f('p50_ms'), f('ref_p50_ms'), f('p50_ratio', unit='×'), '≤ 1.5×'],
            ['latency p99', f('p99_ms'), f('ref_p99_ms'), f('p99_ratio', unit='×'), '≤ 1.5×'],
            [
                'samples stepped, share of the configured rate',
                f('rate_ratio', '{:.1f}', ' %', 100.0),
                '',
                '',
                '≥ 99 %',
            ],
            [
                'samples superseded before their step',
                f('superseded_hz', '{:.0f}', ' /s'),
                '',
                '',
                '',
            ],
        ],
    ) + ['', f'{len(runs)} run(s) of {span(col(runs, "seconds"), "{:.0f}", " s")} each.']


def table_trace(runs):
    r = runs[-1]
    p50, p90 = r['trace_p50_ms'], r['trace_p90_ms']
    body = [[k, f'{v:.2f}', f'{p90[k]:.2f}'] for k, v in p50.items() if k != 'total']
    body.append(
        [
            '**total** (frame in the kernel → both current frames sent)',
            f'{p50["total"]:.2f}',
            f'{p90["total"]:.2f}',
        ]
    )
    return rows(['segment', 'p50 (ms)', 'p90 (ms)'], body) + [
        '',
        f"The probes' p50 in the same run: {r['p50_ms']:.2f} ms, {r['p50_ratio']:.2f}× the bare "
        f"chain (the trace's own writes cost a little); {r['traced_samples']} samples traced.",
    ]


def read_mujoco(out):
    cases = grab_all(
        r'^(\S.*?)\s+([\d.]+)x real time\s+\(\s*([\d.]+) us/step, ([\d.]+)x the reference\)', out
    )
    return {name.strip(): (float(rt), float(us), float(ratio)) for name, rt, us, ratio in cases}


def table_mujoco(runs):
    names = list(runs[0])
    body = [
        (
            name,
            span([r[name][0] for r in runs], '{:.1f}', '×'),
            span([r[name][1] for r in runs], '{:.1f}'),
            span([r[name][2] for r in runs], '{:.2f}', '×'),
            '≥ 20×' if name.startswith('plant at 1 kHz') else '',
        )
        for name in names
    ]
    return rows(
        ['case', 'real-time factor', 'µs per physics step', 'against bare mj_step', 'goal'], body
    )


def read_wire(out):
    found = grab_all(
        r'^(\S.*?)\s+publish: object\s+([\d.]+), bytes\s+([\d.]+) .*take and read: object\s+'
        r'([\d.]+), bytes\s+([\d.]+)',
        out,
    )
    return {'rows': [[m[0], *(float(v) for v in m[1:])] for m in found]}


def table_wire(runs):
    body = [
        [
            label,
            f'{po:.1f}',
            f'{pb:.1f}',
            f'{po / pb:.1f}×',
            f'{to:.1f}',
            f'{tb:.1f}',
            f'{to / tb:.1f}×',
        ]
        for label, po, pb, to, tb in runs[-1]['rows']
    ]
    return rows(
        [
            'message',
            'publish: object (µs)',
            'bytes (µs)',
            'ratio',
            'take and read: object (µs)',
            'bytes (µs)',
            'ratio',
        ],
        body,
    )


def read_sim_speed(out):
    procs = grab_all(
        r'^processes, real_time_factor ([\d.]+): ([\d.]+)x real time.*?([\d.]+) ms wall per '
        r'sample, of which ([\d.]+) ms waiting.*?lockstep misses (\d+)',
        out,
    )
    return {
        'processes': {float(m[0]): [float(m[1]), float(m[2]), int(m[4])] for m in procs},
        'composed': grab(r'^composed: ([\d.]+)x real time', out),
        'composed_ms': grab(r'^composed: .*?([\d.]+) ms wall per sample', out),
        'rate_hz': grab(r'^composed: .*? at ([\d.]+) Hz', out),
    }


PLANT_LABELS = {'reduced': 'reduced', 'mujoco': 'MuJoCo'}
PLANTS = tuple(PLANT_LABELS)
# what differs between the plants, and why (docs/mujoco.md)
PLANTS_DIFFER = (
    "The reduced plant integrates the controller's own model (the locked pose as one rigid body "
    'on the axle, `krang_model/wip.py`); the MuJoCo plant is the full body from the URDF at 1 kHz '
    "physics, with the wheels and the caster on the floor by contact and the arms' momentum "
    '([mujoco.md](mujoco.md)): physics the controller was not designed from, at about ten times '
    'the CPU per physics step (the WIP simulation and MuJoCo sections above), a difference that '
    'grows with the physics steps per control sample: 10 at 100 Hz, 2 at 500 Hz.'
)


def per_plant(by_plant, figure):
    """One cell per plant: `figure(runs)` of each plant's runs."""
    return [figure(runs) for runs in by_plant.values()]


def plant_header(by_plant, what):
    return [f'{what}: {PLANT_LABELS.get(p, p)}' for p in by_plant]


def table_sim_speed(by_plant, goal=''):
    """A row per way of running the node set, its figures per plant side by side; `goal` is the
    composed node set's goal (a column of its own when given)."""
    factors = sorted(
        {f for runs in by_plant.values() for r in runs for f in r['processes']}, reverse=True
    )
    body = []
    for f in factors:

        def got(runs, i, f=f):
            return [r['processes'][f][i] for r in runs if f in r['processes']]

        what = 'processes, paced (real_time_factor 1)' if f else 'processes, unpaced (0)'
        if f not in (0.0, 1.0):
            what = f'processes, real_time_factor {f:g}'
        body.append(
            [
                what,
                *per_plant(by_plant, lambda runs: span(got(runs, 0), unit='×')),
                *per_plant(by_plant, lambda runs: span(got(runs, 1))),
                *per_plant(by_plant, lambda runs: span(got(runs, 2), '{:.0f}')),
            ]
            + ([''] if goal else [])
        )
    body.append(
        [
            'composed (one process, as `krang demo`)',
            *per_plant(by_plant, lambda runs: span(col(runs, 'composed'), unit='×')),
            *per_plant(by_plant, lambda runs: span(col(runs, 'composed_ms'))),
            *per_plant(by_plant, lambda runs: '–'),
        ]
        + ([goal] if goal else [])
    )
    header = [
        'node set while balancing',
        *plant_header(by_plant, 'real-time factor'),
        *plant_header(by_plant, 'ms wall per sample'),
        *plant_header(by_plant, 'lockstep misses'),
    ]
    return rows(header + (['goal'] if goal else []), body) + [
        '',
        ' '.join([PLANTS_DIFFER, *composed_against(by_plant)]),
    ]


def composed_against(by_plant):
    """How the composed node set's speed on each plant compares with the first plant's, and the
    extra wall time per sample against the physics steps a sample takes (1 kHz physics)."""
    (first, ref), *others = by_plant.items()
    said = []
    for plant, runs in others:
        ratio = span([r['composed'] / b['composed'] for r, b in zip(runs, ref)])
        extra = span([r['composed_ms'] - b['composed_ms'] for r, b in zip(runs, ref)], '{:+.2f}')
        steps = span([1e3 / r['rate_hz'] for r in runs], '{:.0f}')
        said.append(
            f'Composed, the {PLANT_LABELS.get(plant, plant)} plant runs at {ratio}× the '
            f"{PLANT_LABELS.get(first, first)} plant's speed, {extra} ms wall time per sample "
            f'({steps} physics steps a sample).'
        )
    return said


def read_demo(out):
    fig = last_json(out)
    fig['wall_s'] = float(grab(r'^WALL ([\d.]+)$', out))
    return fig


def table_demo(by_plant):
    mm = 1e3

    def error(runs):
        before = span([r['com_error_before_m'] * mm for r in runs], '{:.1f}')
        after = span([r['com_error_after_m'] * mm for r in runs], '{:.2f}')
        return f'{before} → {after} mm'

    return rows(
        ['figure', *(f'{PLANT_LABELS.get(p, p)} plant' for p in by_plant)],
        [
            [
                'wall time',
                *per_plant(by_plant, lambda runs: span(col(runs, 'wall_s'), '{:.1f}', ' s')),
            ],
            [
                'poses learned',
                *per_plant(by_plant, lambda runs: span(col(runs, 'poses'), '{:.0f}')),
            ],
            ['forward CoM error before → after', *per_plant(by_plant, error)],
        ],
    ) + ['', PLANTS_DIFFER]


SECTIONS = [
    Section('phi', 'The CoM regressor phi(q)', ['PY', 'bench/bench_phi.py'], read_phi, table_phi),
    Section('wip_sim', 'WIP simulation', ['PY', 'bench/bench_wip_sim.py'], read_wip, table_wip),
    Section(
        'pose_pool',
        'The safe balanced pose pool',
        ['PY', 'bench/bench_pose_pool.py'],
        read_pool,
        table_pool,
    ),
    Section(
        'pose_filter',
        "The meta-learning pose filter (Algorithm 1) at the paper's scale",
        ['PY', 'bench/bench_pose_filter.py', '--full'],
        read_filter,
        table_filter,
    ),
    Section(
        'closed_loop',
        "The offline closed loop and the controller's step",
        ['PY', 'bench/bench_closed_loop.py'],
        read_closed_loop,
        table_closed_loop,
    ),
    Section(
        'discrepancy',
        'One `krang discrepancy` run',
        ['PY', 'bench/bench_discrepancy.py', '--no-plots'],
        read_discrepancy,
        table_discrepancy,
    ),
    Section(
        'discrepancy_validation',
        'The discrepancy workflow: one hidden effect per record',
        ['PY', 'bench/bench_discrepancy.py', '--validate'],
        markdown_lines,
        table_markdown,
        about='22 s simulated records, one hidden effect each, plus none.',
    ),
    Section(
        'discrepancy_hidden',
        'The discrepancy workflow: effects it is not told of',
        ['PY', 'bench/bench_discrepancy.py', '--hidden'],
        markdown_lines,
        table_markdown,
        about='No-effect records at several noise levels and seeds, small effects, pairs, and '
        'effects outside the library (which must read `unexplained`).',
    ),
    Section(
        'imu_bias',
        'The IMU filter: gyro-bias tracking against pitch error',
        ['PY', 'bench/bench_imu_bias.py'],
        read_imu_bias,
        table_imu_bias,
        about='The trade-off behind the configured bias process noise ([imu.md](imu.md)).',
    ),
    Section(
        'ros_latency',
        "The control path on the robot's configuration",
        ['PY', 'bench/bench_ros_latency.py', '--robot', '--json'],
        read_latency,
        table_latency,
        about='A DMU frame on the bus to the wheel-command frame answering it, through '
        "`can_bridge` and `adrc_controller` at 500 Hz under SCHED_FIFO (the robot's parameter "
        'files), against a bare rclpy chain (CAN → process → topic → process → topic → CAN) '
        'measured alone beside the same device players just before. The players keep a 1 Mbit/s '
        "bus's pace and the drives' TPDO phase sweeps the sample period ([architecture.md]"
        '(architecture.md), "The latency benchmark").',
        runs=3,
        json_mode=True,
    ),
    Section(
        'ros_latency_load',
        'The control path with two busy loops on the machine',
        ['PY', 'bench/bench_ros_latency.py', '--robot', '--json', '--load', '2'],
        read_latency,
        table_latency,
        about='As above, with two busy-loop processes beside the nodes.',
        json_mode=True,
    ),
    Section(
        'ros_latency_trace',
        "Where a sample's time goes on the control path",
        ['PY', 'bench/bench_ros_latency.py', '--robot', '--trace', '--json'],
        read_latency,
        table_trace,
        json_mode=True,
        about='Each node records when a sample passes each stage (`krang_ros/trace.py`); the '
        'segments of one sample add up to its total.',
    ),
    Section(
        'mujoco',
        'The full-body MuJoCo plant',
        ['PY', 'bench/bench_mujoco.py'],
        read_mujoco,
        table_mujoco,
        about='`krang_sim/mujoco_plant.py` at 1 kHz physics, best of the repeats; the reference '
        'is '
        "MuJoCo's own `mj_step` on the same model in the same run ([mujoco.md](mujoco.md)).",
    ),
    Section(
        'wire',
        'A control-path message as an rclpy object and as its bytes',
        ['PY', 'bench/bench_wire.py'],
        read_wire,
        table_wire,
        about='CPU per message in one process over DDS, best of 5 batches of 2,000 '
        '(`krang_ros/wire.py`).',
    ),
    Section(
        'sim_speed',
        "The simulated node set at 100 Hz (the simulator's rate)",
        ['PY', 'bench/bench_sim_speed.py'],
        read_sim_speed,
        table_sim_speed,
        about='sim_krang, can_bridge and adrc_controller in lockstep while balancing '
        '([simulation.md](simulation.md)), on each plant (P).',
        plants=PLANTS,
    ),
    Section(
        'sim_speed_500',
        "The simulated node set at 500 Hz (the robot's rate)",
        ['PY', 'bench/bench_sim_speed.py', '--factors', '0', '--rate-hz', '500'],
        read_sim_speed,
        lambda by_plant: table_sim_speed(by_plant, goal='≥ 1×'),
        about='As above, with the sample and control rate at 500 Hz.',
        plants=PLANTS,
    ),
    Section(
        'demo',
        '`krang demo`, 3 poses',
        ['KRANG', 'demo', '--out', 'OUT'],
        read_demo,
        table_demo,
        json_mode=True,
        about='The composed node set with the default truth and seed, on each plant (P); a '
        'plant learns the same beta to the bit in every run.',
        plants=PLANTS,
    ),
]
BY_NAME = {s.name: s for s in SECTIONS}


# ---- running and writing ------------------------------------------------------------------------
def run_once(section, plant=None):
    """stdout of one run of the section's benchmark (raises ReportError when it fails)."""
    with tempfile.TemporaryDirectory(prefix='krang_report_') as tmp:
        argv = section.argv_to_run(tmp, plant)
        t0 = time.monotonic()
        proc = subprocess.run(
            argv, cwd=ROOT, capture_output=True, text=True, env={**os.environ, **section.env}
        )
        wall = time.monotonic() - t0
    if proc.returncode != 0:
        tail = '\n'.join(proc.stderr.strip().splitlines()[-5:])
        on = f' (P: {plant})' if plant else ''
        raise ReportError(f'{section.command()}{on} exited with {proc.returncode}:\n{tail}')
    return proc.stdout + f'\nWALL {wall:.3f}\n'


def run_section(section, runs):
    """The figures of `runs` runs of the section (a list, or {plant: list} with plants), and the
    machine's 1-minute load average as each run started (timings on a shared machine)."""
    loads = []

    def one(plant=None):
        loads.append(os.getloadavg()[0])
        return section.read(run_once(section, plant))

    if not section.plants:
        return [one() for _ in range(runs)], loads
    return {p: [one(p) for _ in range(runs)] for p in section.plants}, loads


def render(section, runs, loads=()):
    """The markdown of one section, markers included (`loads`: see run_section)."""
    lines = [f'<!-- bench: {section.name} -->', f'## {section.title}', '']
    if section.about:
        lines += [section.about, '']
    command = f'`{section.command()}`'
    if section.plants:
        command += ', P: ' + ', '.join(f'`{p}`' for p in section.plants)
    lines += [command, '']
    lines += section.table(runs)
    if loads:
        lines += [
            '',
            'Load average (1 min) as each run started: '
            + ', '.join(f'{x:.1f}' for x in loads)
            + f' ({os.cpu_count()} cores).',
        ]
    lines += ['<!-- /bench: ' + section.name + ' -->', '']
    return '\n'.join(lines) + '\n'


def split(text):
    """{name: block text with its markers} of an existing document, and the text before the
    first block (kept as the document's head)."""
    blocks = {m.group(1): m.group(0) for m in BLOCK.finditer(text)}
    first = BLOCK.search(text)
    head = text[: first.start()] if first else text
    return head, blocks


def assemble(head, blocks):
    """The document: its head, then the sections in SECTIONS order, then any unknown block kept
    as it was (a section this script does not make is kept, never dropped silently)."""
    known = [blocks[s.name] for s in SECTIONS if s.name in blocks]
    unknown = [b for n, b in blocks.items() if n not in BY_NAME]
    body = [b if b.endswith('\n\n') else b.rstrip('\n') + '\n\n' for b in known + unknown]
    return (head or HEADER) + ''.join(body).rstrip('\n') + '\n'


def check(path):
    """Problems of an existing document: sections missing, unknown or empty."""
    if not path.exists():
        return [f'{path}: no such file']
    _, blocks = split(path.read_text())
    problems = [f'section {s.name!r} missing' for s in SECTIONS if s.name not in blocks]
    problems += [
        f'section {n!r} is not made by bench/report.py' for n in blocks if n not in BY_NAME
    ]
    problems += [f'section {n!r} has no table' for n, b in blocks.items() if '\n|' not in b]
    return problems


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument(
        '--only',
        nargs='+',
        metavar='NAME',
        choices=list(BY_NAME),
        help='rerun these sections only; the others keep their text',
    )
    p.add_argument('--runs', type=int, default=None, help='runs per section (default: its own)')
    p.add_argument('--out', type=Path, default=DEFAULT_OUT, help='the document to write')
    p.add_argument('--list', action='store_true', help='print the sections and their commands')
    p.add_argument('--check', action='store_true', help='check the document; run nothing')
    args = p.parse_args(argv)
    if args.list:
        for s in SECTIONS:
            mode = 'json' if s.json_mode else 'text'
            print(f'{s.name:24s} runs {s.runs}  {mode}  {s.command()}')
        return 0
    if args.check:
        problems = check(args.out)
        for line in problems:
            print(f'{args.out.name}: {line}')
        return 1 if problems else 0
    head, blocks = split(args.out.read_text()) if args.out.exists() else ('', {})
    failed = []
    for s in [BY_NAME[n] for n in args.only] if args.only else SECTIONS:
        print(f'{s.name}: {s.command()}', flush=True)
        try:
            runs, loads = run_section(s, args.runs or s.runs)
            blocks[s.name] = render(s, runs, loads)
        except (ReportError, ValueError, KeyError) as exc:
            failed.append(s.name)
            print(f'{s.name}: {exc}; its section is kept as it was', file=sys.stderr)
            continue
        args.out.write_text(assemble(head, blocks))  # each section as soon as it is done
    if not blocks:
        args.out.write_text(assemble(head, blocks))
    if failed:
        print(f'failed: {", ".join(failed)}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
