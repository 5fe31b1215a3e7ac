"""The operator's long requests as goals (adrc_controller's stand_up and sit_down actions): what
each waits for, and how it ends, from the modes and events of the controller's steps. Pure: the
node feeds it each step that changed something and turns an ending into the action's result.

- stand_up ends in success when the controller balances, and fails when the mode machine refuses
  the stand or the controller goes anywhere else (a safe stop, a sit-down). A try caught back on
  the caster is retried (stand.py) and the goal goes on; it fails when the tries are used up.
- sit_down ends in success on the caster (sit), and fails on a refused sit or a safe stop.
- Cancelling a stand-up sits the robot back down when it can (`sitting_back`): the goal ends,
  cancelled, on the caster.
"""

from __future__ import annotations

from dataclasses import dataclass

from .stand import EXHAUSTED

STAND_UP = 'stand_up'
SIT_DOWN = 'sit_down'


@dataclass(frozen=True)
class Ending:
    success: bool
    message: str
    cancelled: bool = False


@dataclass
class OperatorGoal:
    kind: str  # STAND_UP | SIT_DOWN
    started: float  # the node's clock when accepted [s]
    cancel_requested: bool = False
    sitting_back: bool = False  # a cancelled stand-up: the sit-down it asked for is under way

    def after_step(self, mode: str, events: list[str]) -> Ending | None:
        """How the goal ends after a step that left the controller in `mode` (a Mode value)
        with `events` (ControlOutput.events), or None while it goes on."""
        if mode == 'safe_stop':
            return Ending(False, f'safe stop: {stop_reason(events)}')
        if self.kind == STAND_UP:
            if self.sitting_back:
                return Ending(False, 'cancelled: sat back down', True) if mode == 'sit' else None
            if mode == 'balance':
                return Ending(True, 'balancing')
            if mode == 'sit':
                why = _refusal(events, 'stand_refused')
                if why is not None:
                    return Ending(False, f'refused: {why}')
                why = _refusal(events, 'sit reason')
                if why is not None and why.endswith(EXHAUSTED):
                    return Ending(False, why)
                return None
            if mode == 'sit_down':
                return Ending(False, 'a sit-down was requested while standing up')
            return None
        if mode == 'sit':
            return Ending(True, 'sitting on the caster')
        why = _refusal(events, 'sit_refused')
        return None if why is None else Ending(False, f'refused: {why}')


def stop_reason(events: list[str]) -> str:
    """Why the controller stopped, from a step's events ('stop reason: ...' if given, else the
    transition's own reason)."""
    for event in events:
        if event.startswith('stop reason: '):
            return event[len('stop reason: ') :]
    for event in events:
        if '->safe_stop: ' in event:
            return event.split('->safe_stop: ', 1)[1]
    return 'the controller left for safe_stop'


def _refusal(events, prefix):
    for event in events:
        if event.startswith(prefix + ': '):
            return event[len(prefix) + 2 :]
    return None
