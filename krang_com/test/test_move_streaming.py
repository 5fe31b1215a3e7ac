"""The pose server's streaming core (krang_pose_server.streaming): a move holds its setpoint while
the controller's balance flag is false, resumes when it returns, pauses at most max_pause_s in
total, and then runs the rest at slow_fraction of its speed to the end."""

import numpy as np
import pytest

from krang_pose_server.sequence import StraightLineMove
from krang_pose_server.streaming import MoveStreamer, PauseConfig

DT = 0.05


def move(duration=2.0):
    return StraightLineMove(np.zeros(2), np.array([1.0, -2.0]), duration)


def run(streamer, flags):
    """Advance once per flag; returns the setpoints and the events."""
    points, events = [], []
    for flag in flags:
        events.append(streamer.advance(DT, flag))
        points.append(streamer.setpoint)
    return np.array(points), events


def test_an_uninterrupted_move_runs_at_full_speed():
    s = MoveStreamer(move(2.0))
    points, events = run(s, [True] * 40)
    assert s.done and s.pauses == 0 and s.paused_s == 0.0
    assert not any(events)
    np.testing.assert_allclose(points[19], [0.5, -1.0])
    np.testing.assert_allclose(points[-1], [1.0, -2.0])


def test_a_false_flag_holds_the_setpoint_and_true_resumes():
    s = MoveStreamer(move(2.0), PauseConfig(max_pause_s=10.0))
    points, events = run(s, [True] * 10 + [False] * 30 + [True] * 30)
    np.testing.assert_allclose(points[9:40], np.repeat(points[9:10], 31, axis=0))
    assert events[10] == 'pause' and events[40] == 'resume'
    assert s.pauses == 1 and s.paused_s == pytest.approx(1.5)
    assert s.done and not s.slow  # 2 s of path in 2 s of true flags
    np.testing.assert_allclose(points[69], [1.0, -2.0])
    assert not np.allclose(points[68], points[69])


def test_pauses_add_up_to_at_most_max_pause_then_the_rest_is_slow():
    s = MoveStreamer(move(2.0), PauseConfig(max_pause_s=1.0, slow_fraction=0.25))
    flags = [True] * 10 + [False] * 12 + [True] * 2 + [False] * 200
    points, events = run(s, flags)
    assert events.count('pause') == 2 and events.count('resume') == 1
    assert 'slow' in events and s.slow
    assert s.paused_s == pytest.approx(1.0)
    # 0.6 s of path before the budget ran out, then 0.25 s of path per s
    k = events.index('slow')
    steps = np.diff(points[k + 1 :, 0])
    steps = steps[steps > 1e-9]
    np.testing.assert_allclose(steps, 0.25 * DT / 2.0)
    assert s.done
    np.testing.assert_allclose(points[-1], [1.0, -2.0])


def test_a_move_always_ends_within_its_bound():
    cfg = PauseConfig(max_pause_s=3.0, slow_fraction=0.5)
    s = MoveStreamer(move(2.0), cfg)
    n = 0
    while not s.done:
        s.advance(DT, False)
        n += 1
    assert n * DT <= 3.0 + 2.0 / 0.5 + DT


def test_parameters_are_checked():
    with pytest.raises(ValueError):
        PauseConfig(max_pause_s=-1.0)
    with pytest.raises(ValueError):
        PauseConfig(slow_fraction=0.0)
