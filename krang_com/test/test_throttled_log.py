"""krang_core.log.Throttled: a throttled line is checked against the clock before anything else."""

import time

from krang_core.log import Throttled


def test_logs_at_most_once_a_period_and_again_after_it():
    lines = []
    warn = Throttled(lines.append, 0.2)
    start = time.monotonic()
    logged = [warn(f'line {k}') for k in range(1000)]
    assert time.monotonic() - start < 0.2  # the whole burst fell inside one period
    assert lines == ['line 0'] and logged == [True] + [False] * 999
    time.sleep(0.25)
    assert warn('later') is True
    assert lines == ['line 0', 'later']


def test_each_call_site_has_its_own_period():
    lines = []
    a, b = Throttled(lines.append, 10.0), Throttled(lines.append, 10.0)
    a('a1'), b('b1'), a('a2'), b('b2')
    assert lines == ['a1', 'b1']
