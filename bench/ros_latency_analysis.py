"""The latency figures of bench_ros_latency.py --robot from what the players recorded (plain
numpy): which wheel command answers which DMU sample, the probes' answers, the reference chain's
latencies, the p50 by where in the period the drives' next TPDO set came, and the rates of the
nodes' diagnostics."""

import math

import numpy as np

MIN_PROBES = 20  # answered probes needed for percentiles by probe
TPDO_PARTS = 5  # p50_by_next_tpdo: the sample period in fifths (0.4 ms at 500 Hz)
JSON_KEYS = ('p50_ms', 'p99_ms', 'rate_hz', 'configured_rate_hz', 'ref_p50_ms', 'ref_p99_ms')


def new_commands(t, value):
    """The RPDOs of one drive that carry a new current (a repeat of the previous payload is the
    bridge's periodic refresh); sorted by time."""
    order = np.argsort(t, kind='stable')
    t, value = np.asarray(t, float)[order], np.asarray(value, float)[order]
    keep = np.ones(len(t), bool)
    keep[1:] = value[1:] != value[:-1]
    return t[keep], value[keep]


def timing_match(sample_t, cmd_t):
    """Each command answers the newest sample before it; a sample's latency is its first such
    command. Returns (latencies of the answered samples [s], number of distinct samples answered).
    """
    idx = np.searchsorted(sample_t, cmd_t, side='right') - 1
    ok = idx >= 0
    idx, ct = idx[ok], cmd_t[ok]
    first = np.unique(idx, return_index=True)[1]
    return ct[first] - sample_t[idx[first]], len(first)


def probe_match(sample_t, probe, cmd_t, cmd_v):
    """Latencies of the answered probe samples [s], the probes' response (DC2 units) and the
    times of those samples.

    `probe`: per sample, the probe's sign (+1, -1; 0 = not a probe). For each probe: baseline =
    the last new command before it, changes = (command - baseline) * sign up to the probe after
    next (the next one moves the other way, so no command before that one's answer is confused
    with this one's). The response is the median of the larger half of the probes' largest
    changes (the probes whose sample reached the controller). A probe's answer is the first
    command whose change exceeds half the response."""
    idx = np.flatnonzero(probe)
    if len(idx) < 3:
        return np.array([]), 0.0, np.array([])
    starts, signs = sample_t[idx], probe[idx].astype(float)
    spacing = float(np.median(np.diff(starts)))
    ends = np.append(starts[2:], starts[-2:] + 2.0 * spacing)
    base_idx = np.searchsorted(cmd_t, starts, side='right') - 1
    windows = []
    for t0, t1, sign, b in zip(starts, ends, signs, base_idx):
        hi = np.searchsorted(cmd_t, t1, side='right')
        if b >= 0 and hi > b + 1:
            windows.append((t0, cmd_t[b + 1 : hi], sign * (cmd_v[b + 1 : hi] - cmd_v[b])))
    if not windows:
        return np.array([]), 0.0, np.array([])
    largest = np.array([d.max() for _, _, d in windows])
    response = float(np.median(np.sort(largest)[len(largest) // 2 :]))
    latencies, times = [], []
    for t0, ts, d in windows:
        hit = np.flatnonzero(d > 0.5 * response)
        if hit.size and response > 0:
            latencies.append(ts[hit[0]] - t0)
            times.append(t0)
    return np.array(latencies), response, np.array(times)


def noise_level(cmd_t, cmd_v, before, seconds=1.0):
    """Robust standard deviation of the new commands in the `seconds` before `before` (the first
    probe), DC2 units."""
    v = cmd_v[(cmd_t >= before - seconds) & (cmd_t < before)]
    return 1.4826 * float(np.median(np.abs(v - np.median(v)))) if len(v) else float('inf')


def reference_latencies(req, ans, window):
    """(latencies [s] of the reference frames sent in the window, number of them unanswered,
    times of the answered ones)."""
    req = req[(req[:, 0] >= window[0]) & (req[:, 0] <= window[1])]
    answers = {}
    for t, n in ans:
        answers.setdefault(int(n), t)
    answered = np.array([(t, answers[int(n)] - t) for t, n in req if int(n) in answers])
    answered = answered.reshape(-1, 2)
    return answered[:, 1], len(req) - len(answered), answered[:, 0]


def p50_by_next_tpdo(times, latencies, tpdo_t, period, parts=TPDO_PARTS):
    """The median latency [ms] of the samples at `times` by when the drives' next TPDO set came
    after each: one value per `parts`-th of the sample period (the first: within a fifth of a
    period after the sample), nan where none; a sample whose next set came more than a period
    later (a set sent late) is in none. The TPDO sets' phase sweeps the period
    (--tpdo-drift-ppm); where they collide with a sample's path through the nodes shows here."""
    tpdo_t = np.sort(tpdo_t)
    k = np.searchsorted(tpdo_t, times, side='right')
    ok = k < len(tpdo_t)
    after = (tpdo_t[k[ok]] - times[ok]) / period
    latencies = np.asarray(latencies)[ok]
    part = np.floor(after * parts).astype(int)
    return [
        float(1e3 * np.median(latencies[part == i])) if np.any(part == i) else float('nan')
        for i in range(parts)
    ]


def tpdo_phases_seen(sample_t, tpdo_t, window, bins=10):
    """The share of `bins` equal parts of the sample period in which TPDO sets were sent during
    `window`, their phase taken from the sample before each: near 1 when the phase sweeps the
    period (--tpdo-drift-ppm), one or two tenths when it stays put."""
    st = np.sort(sample_t)
    t = tpdo_t[(tpdo_t >= window[0]) & (tpdo_t <= window[1])]
    k = np.searchsorted(st, t) - 1
    t, k = t[k >= 1], k[k >= 1]
    if not len(t):
        return float('nan')
    period = float(np.median(np.diff(st)))
    phase = np.clip((t - st[k]) / period, 0.0, 0.999)
    return len(np.unique((phase * bins).astype(int))) / bins


def count_rates(reports, window, columns):
    """Per second, each of `columns` counts of 1 Hz reports (stamp, count, ...): between the
    first report in the window and the last (nan for each without two)."""
    inside = [r for r in reports if window[0] <= r[0] <= window[1]]
    if len(inside) < 2:
        return (float('nan'),) * columns
    first, last = inside[0], inside[-1]
    return tuple((last[k] - first[k]) / (last[0] - first[0]) for k in range(1, columns + 1))


def analyse(record, window, rate_hz, diag=(), ref_window=None, bridge_diag=()):
    """Figures of one --robot run from the player's record, the controller's diagnostics (1 Hz
    reports (stamp, samples_stepped, samples_superseded)) and the bridge's ((stamp, /imu/data
    samples published)), see the module docstring; the reference chain's from `ref_window`
    (default `window`)."""
    w0, w1 = window
    duration = w1 - w0
    left = record['cmd_id'] == int(record['left_id'])
    cmd_t, cmd_v = new_commands(record['cmd_t'][left], record['cmd_value'][left])
    st, probe = record['sample_t'], record['sample_probe']
    inside = (st >= w0) & (st <= w1)
    period = 1.0 / rate_hz
    in_cmd = (cmd_t >= w0) & (cmd_t <= w1 + 10 * period)
    t_lat, answered = timing_match(st[inside], cmd_t[in_cmd])
    p_lat, response, p_t = probe_match(st[inside], probe[inside], cmd_t, cmd_v)
    noise = noise_level(cmd_t, cmd_v, st[probe != 0][0]) if probe.any() else float('inf')
    probes = int(np.count_nonzero(probe[inside]))
    # a probe's answer must stand well above the command noise to carry its identity
    by_probe = len(p_lat) >= MIN_PROBES and abs(response) > 5.0 * noise
    lat = p_lat if by_probe else t_lat
    ref_lat, ref_lost, ref_t = reference_latencies(
        record['ref_req'], record['ref_ans'], ref_window or window
    )
    cmd_in = (cmd_t >= w0) & (cmd_t <= w1)
    r0, r1 = ref_window or window
    tpdo_t = record['tpdo_t']
    ms = lambda x, q: float(1e3 * np.percentile(x, q)) if len(x) else float('nan')  # noqa: E731
    late = record['sample_late'][inside]  # how late the player sent each sample
    stepped, superseded = count_rates(diag, window, 2)
    (published,) = count_rates(bridge_diag, window, 1)
    out = {
        'p50_ms': ms(lat, 50),
        'p99_ms': ms(lat, 99),
        'rate_hz': stepped,
        'configured_rate_hz': rate_hz,
        'ref_p50_ms': ms(ref_lat, 50),
        'ref_p99_ms': ms(ref_lat, 99),
    }
    out.update(
        {
            'p50_ratio': out['p50_ms'] / out['ref_p50_ms'],
            'p99_ratio': out['p99_ms'] / out['ref_p99_ms'],
            'rate_ratio': out['rate_hz'] / rate_hz,
            'bus_rate_hz': answered / duration,
            'superseded_hz': superseded,
            'match': 'probe' if by_probe else 'timing',
            'timing_p50_ms': ms(t_lat, 50),
            'timing_p99_ms': ms(t_lat, 99),
            'max_ms': float(1e3 * lat.max()) if len(lat) else float('nan'),
            'probes': probes,
            'probes_answered': len(p_lat),
            'probe_response_dc2': response,
            'command_noise_dc2': noise,
            'dmu_rate_hz': int(inside.sum()) / duration,
            'dmu_late_hz': int(np.count_nonzero(late > period)) / duration,
            'dmu_max_late_ms': float(1e3 * late.max(initial=0.0)),
            'bridge_imu_rate_hz': published,
            'tpdo_rate_hz': int(np.count_nonzero((tpdo_t >= w0) & (tpdo_t <= w1))) / duration,
            'tpdo_phases_seen': tpdo_phases_seen(st, tpdo_t, window),
            'p50_by_next_tpdo_ms': (
                p50_by_next_tpdo(p_t, p_lat, tpdo_t, period)
                if by_probe  # else the probes carry no identity (the JSON's `match`)
                else [math.nan] * TPDO_PARTS
            ),
            'ref_p50_by_next_tpdo_ms': p50_by_next_tpdo(ref_t, ref_lat, tpdo_t, period),
            'ref_tpdo_rate_hz': int(np.count_nonzero((tpdo_t >= r0) & (tpdo_t <= r1))) / (r1 - r0),
            'new_commands_hz': int(cmd_in.sum()) / duration,
            'ref_frames': len(ref_lat) + ref_lost,
            'ref_lost': ref_lost,
            'seconds': duration,
        }
    )
    return out
