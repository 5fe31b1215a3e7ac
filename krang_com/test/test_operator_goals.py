"""How the controller's stand_up and sit_down goals end, from the modes and events of its steps
(krang_adrc_controller.goals; over real processes: test_controller_services.py)."""

from krang_adrc_controller.goals import SIT_DOWN, STAND_UP, Ending, OperatorGoal
from krang_adrc_controller.modes import ModesConfig, SafetyConfig


def test_a_stand_up_ends_balancing_or_says_why_not():
    goal = OperatorGoal(STAND_UP, 0.0)
    assert goal.after_step('stand_up', ['sit->stand_up: stand request']) is None
    assert goal.after_step('balance', ['stand_up->balance: stood up and settled']) == Ending(
        True, 'balancing'
    )
    refused = OperatorGoal(STAND_UP, 0.0).after_step('sit', ['stand_refused: CoM-angle error'])
    assert refused == Ending(False, 'refused: CoM-angle error')
    stopped = OperatorGoal(STAND_UP, 0.0).after_step(
        'safe_stop', ['stand_up->safe_stop: stop request', 'stop reason: operator halt']
    )
    assert stopped == Ending(False, 'safe stop: operator halt')
    sat = OperatorGoal(STAND_UP, 0.0).after_step('sit_down', ['stand_up->sit_down: sit request'])
    assert not sat.success and 'sit-down' in sat.message


def test_a_stand_up_goes_on_through_its_caught_tries_and_fails_when_they_are_used_up():
    from krang_adrc_controller.stand import StandUp

    stand = StandUp(ModesConfig(stand_tries=2), SafetyConfig(), -1.76, 0.002)
    goal = OperatorGoal(STAND_UP, 0.0)
    caught = ['stand_up->sit: fell back on the caster while standing up']
    stand.tries = 1
    assert goal.after_step('sit', caught + [f'sit reason: {stand.why()}']) is None
    stand.tries = 2
    ending = goal.after_step('sit', caught + [f'sit reason: {stand.why()}'])
    assert ending == Ending(False, stand.why()) and 'try 2 of 2' in ending.message


def test_a_cancelled_stand_up_ends_cancelled_on_the_caster():
    goal = OperatorGoal(STAND_UP, 0.0, cancel_requested=True, sitting_back=True)
    assert goal.after_step('sit_down', ['stand_up->sit_down: sit request']) is None
    assert goal.after_step('sit', ['sit_down->sit: on the caster']) == Ending(
        False, 'cancelled: sat back down', True
    )


def test_a_sit_down_ends_on_the_caster_or_says_why_not():
    goal = OperatorGoal(SIT_DOWN, 0.0)
    assert goal.after_step('sit_down', ['balance->sit_down: sit request']) is None
    assert goal.after_step('sit', ['sit_down->sit: on the caster']).success
    refused = OperatorGoal(SIT_DOWN, 0.0).after_step('balance', ['sit_refused: waist 2.0 rad'])
    assert refused == Ending(False, 'refused: waist 2.0 rad')
    stale = OperatorGoal(SIT_DOWN, 0.0).after_step('safe_stop', ['sit_down->safe_stop: stale'])
    assert stale == Ending(False, 'safe stop: stale')
