"""The replay's fast path is the model's one integrator.

``krang_model.wip.PitchBatch`` steps the replay's batches with ``WipDynamics.step_pitch`` in place
(``PitchBuffers``, the CoM angle's sine and cosine carried by rotation between exact anchors): the
same equations as a simulator's float step and an array step, bit for bit with an exact anchor at
every step, to rounding otherwise. A prediction does not depend on how its windows are chunked or
on the threads that run the chunks, nor on the other parameter sets of its batch (a set asked for
twice is predicted once); the fits' Levenberg-Marquardt skips the Jacobian of a rejected step,
and the prediction of a step that repeats one it has just rejected, without changing its path.
"""

import tracemalloc
from dataclasses import replace

import numpy as np
import pytest

from krang_discrepancy.fitting import (
    FitJob,
    batched_fit,
    fd_steps,
    interior,
    mean_losses,
    start_value,
)
from krang_discrepancy.nominal import NominalModel
from krang_discrepancy.replay import Replay, ReplayConfig
from krang_discrepancy.synthetic import simulate_record
from krang_model.drivetrain import drivetrain, stack
from krang_model.effects import apply_effects, library, model_terms
from krang_model.robot import load_krang
from krang_model.wip import PitchBatch, WipBody, WipDynamics


def _batch(p=3, s=40, seed=0):
    rng = np.random.default_rng(seed)
    nominal = drivetrain(load_krang())
    drives = [
        replace(nominal, coulomb_friction=c, floor_slope=a, ground_viscous=g)
        for c, a, g in ((0.0, 0.0, 0.0), (2.0, 0.02, 0.0), (5.0, -0.01, 3.0))[:p]
    ]
    body = WipBody(
        mass=np.full((p, 1), 140.0),
        com_distance=rng.uniform(0.15, 0.3, (1, s)),
        com_offset=rng.normal(0.0, 0.05, (1, s)),
        inertia_axle=rng.uniform(15.0, 25.0, (1, s)),
    )
    # pitches around the balance and on the caster (-1.76 rad), so the contact acts in some
    qb = rng.uniform(-1.8, -1.45, (p, s))
    state = [rng.normal(0, 1, (p, s)), qb, rng.normal(0, 2, (p, s)), rng.normal(0, 0.5, (p, s))]
    return stack(drives), body, state, rng.normal(0, 15, (1, s))


def _run(drive, body, state, tau, steps, anchor=None, force=None):
    phi, qb, dphi, dqb = (x.copy() for x in state)
    f = None if force is None else (force, -force)
    if anchor is None:
        dyn = WipDynamics(body, drive)
        for _ in range(steps):
            phi, qb, dphi, dqb = dyn.step_pitch(phi, qb, dphi, dqb, tau, 2e-3, *(f or ()))
        return phi, qb, dphi, dqb
    stepper = PitchBatch(qb.shape, anchor)
    stepper.set_dynamics(WipDynamics(body, drive))
    for _ in range(steps):
        stepper.step(phi, qb, dphi, dqb, tau, 2e-3, *(f or (None, None)))
    return phi, qb, dphi, dqb


@pytest.mark.parametrize('force', [False, True])
def test_pitch_batch_is_step_pitch_bit_for_bit_with_exact_trigonometry(force):
    drive, body, state, tau = _batch()
    f = np.full(state[0].shape, 1.5) if force else None
    want = _run(drive, body, state, tau, 60, force=f)
    got = _run(drive, body, state, tau, 60, anchor=1, force=f)
    for a, b in zip(want, got):
        assert np.array_equal(a, b)


def test_the_batch_steps_the_float_equations_bit_for_bit():
    """Element by element, a simulator's float step (math functions, Python operators) and the
    batch's in-place step run the one statement of the equations: friction, slope, ground
    damping, caster contact and extra forces included."""
    drive, body, state, tau = _batch(s=12, seed=5)
    force = np.linspace(-2.0, 2.0, 12)[None] + np.zeros((3, 1))
    got = _run(drive, body, state, tau, 40, anchor=1, force=force)
    touching = 0
    for p in range(3):
        d = replace(drive, **{k: float(v[p, 0]) for k, v in vars(drive).items() if np.ndim(v)})
        for i in range(12):
            one = WipBody(*(float(np.broadcast_to(v, (3, 12))[p, i]) for v in vars(body).values()))
            dyn = WipDynamics(one, d)
            x = tuple(float(v[p, i]) for v in state)
            f = float(force[p, i])
            for _ in range(40):
                touching += dyn.caster_torque(x[1], x[3]) > 0
                x = dyn.step_pitch(*x, float(tau[0, i]), 2e-3, f, -f)
            assert all(type(v) is float for v in x)
            assert x == tuple(float(v[p, i]) for v in got)
    assert touching > 0  # the caster's branch ran


def test_pitch_batch_carries_sines_and_cosines_to_rounding():
    drive, body, state, tau = _batch(seed=3)
    want = _run(drive, body, state, tau, 150)
    got = _run(drive, body, state, tau, 150, anchor=16)
    for a, b in zip(want, got):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-11 * (1 + np.abs(a).max()))


def test_the_carried_sines_and_cosines_follow_a_body_change():
    """A new body mid-horizon (the replay's moving pose) turns the carried sines and cosines by
    the change of the CoM offset, and the batch still agrees with exact steps to rounding."""
    drive, body, state, tau = _batch(seed=6)
    moved = replace(body, com_offset=body.com_offset + 0.03, com_distance=body.com_distance * 0.9)
    want = [x.copy() for x in state]
    for b in (body, moved):
        dyn = WipDynamics(b, drive)
        for _ in range(70):
            want = dyn.step_pitch(*want, tau, 2e-3)
    got = [x.copy() for x in state]
    stepper = PitchBatch(got[1].shape, 16)
    dyn = WipDynamics(body, drive)
    for b in (body, moved):  # 70 steps: the change falls between two anchors
        dyn = dyn.with_body(b)
        stepper.set_dynamics(dyn)
        for _ in range(70):
            stepper.step(*got, tau, 2e-3)
    for a, b in zip(want, got):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-11 * (1 + np.abs(a).max()))


def test_a_batch_step_allocates_no_arrays():
    """The batch steps in its ``PitchBuffers``: no array of the batch's size is allocated (numpy's
    own iteration buffers are at most 64 kB, an array of this batch is 960 kB)."""
    drive, body, state, tau = _batch(s=40_000, seed=2)
    phi, qb, dphi, dqb = (x.copy() for x in state)
    f_phi = np.full(qb.shape, 0.5)
    f_qbase = -f_phi
    stepper = PitchBatch(qb.shape, 4)
    stepper.set_dynamics(WipDynamics(body, drive))
    assert np.any(qb < drive.caster_contact_pitch)  # the caster's branch runs too
    tracemalloc.start()
    try:
        for _ in range(8):  # exact anchors and rotations
            stepper.step(phi, qb, dphi, dqb, tau, 2e-3, f_phi, f_qbase)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < qb.nbytes / 4


@pytest.fixture(scope='module')
def record():
    return simulate_record({'floor_slope': 0.01}, seconds=8.0, seed=7, hold_s=1.5, sit_down=False)


def test_a_prediction_does_not_depend_on_chunks_or_threads(record):
    model = NominalModel.default()
    lib = {e.key: e for e in library()}
    base = model.terms()
    sets = [base] + [
        apply_effects(base, [lib[k]], [v])
        for k, v in (
            ('torque_constant', 0.8),
            ('payload@lGripper', 2.0),
            ('actuation_delay', 0.01),
            ('floor_slope', 0.02),
            ('wheel_coulomb_friction', 1.0),
        )
    ]
    one = Replay([record], model, ReplayConfig(stride_s=0.05, workers=1))
    two = Replay([record], model, ReplayConfig(stride_s=0.05, workers=2))
    whole = one.predict(sets, max_elements=10**9)
    assert np.array_equal(one.predict(sets, max_elements=500), whole)
    assert np.array_equal(two.predict(sets, max_elements=500), whole)
    # whatever order the windows are asked in
    order = np.random.default_rng(0).permutation(len(one))
    assert np.array_equal(two.predict(sets, order, max_elements=500), whole[:, order])
    traj = two.predict(sets[:2], order, trajectory=True)
    whole_traj = one.predict(sets[:2], trajectory=True, max_elements=10**9)
    for got, want in zip(traj, whole_traj):
        assert np.array_equal(got, want[:, order])
    # each parameter set as it would come out of a batch of its own
    for p, terms in enumerate(sets):
        assert np.array_equal(one.predict([terms])[0], whole[p])


def slope_and_kt_fit(record, config):
    """The replay of `record` and the start of a fit of the floor slope and the torque constant
    from (0, 0.9) on its active windows: (model, replay, base, effects, lo, hi, x, window sets)."""
    model = NominalModel.default()
    rp = Replay([record], model, config)
    base = model.terms()
    rp.set_scales(rp.residuals([base])[0])
    lib = {e.key: e for e in library()}
    effs = [lib['floor_slope'], lib['torque_constant']]
    lo = np.array([e.bounds[0] for e in effs])
    hi = np.array([e.bounds[1] for e in effs])
    x = interior(np.array([0.0, 0.9]), lo, hi)
    return model, rp, base, effs, lo, hi, x, [np.flatnonzero(rp.active)]


def test_skipping_the_jacobian_of_rejected_steps_keeps_the_fit(record):
    """The cost is evaluated first and the Jacobian only at an accepted point: the same path as
    evaluating both at every trial point, with fewer predictions."""
    model, rp, base, effs, lo, hi, x, wsets = slope_and_kt_fit(
        record, ReplayConfig(stride_s=0.1, pose_delay_s=0.01)
    )
    fast = FitJob(list(effs), 0, x.copy(), lo, hi, fd_steps(effs, x, lo, hi))
    batched_fit(rp, base, [fast], wsets)

    def both(replay, b, jobs, ws, need_jac=True):  # the residual and the Jacobian every time
        from krang_discrepancy.fitting import _evaluate

        if need_jac == 'columns':
            return
        _evaluate(replay, b, jobs, ws, True)

    slow = FitJob(list(effs), 0, x.copy(), lo, hi, fd_steps(effs, x, lo, hi))
    batched_fit(rp, base, [slow], wsets, evaluate=both)
    assert np.array_equal(fast.x, slow.x)
    assert fast.iters == slow.iters
    assert fast.nfev <= slow.nfev
    truth = model_terms({'floor_slope': 0.01}, base)
    assert abs(fast.x[0] - truth.drive.floor_slope) < 1e-3


def test_a_parameter_set_asked_for_twice_is_predicted_once(record):
    """A scan's grids each hold the model they start from: equal parameter sets in one batch are
    predicted once and the answer is the one each would get on its own, bit for bit."""
    model = NominalModel.default()
    lib = {e.key: e for e in library()}
    base = model.terms()
    rp = Replay([record], model, ReplayConfig(stride_s=0.1, workers=1))
    kt = apply_effects(base, [lib['torque_constant']], [0.8])
    zeros = [apply_effects(base, [e], [start_value(e, base)]) for e in library()]
    sets = [base, kt, *zeros, kt.copy()]
    got = rp.predict(sets)
    assert rp.timing['predict_sets'] < len(sets)
    for p, terms in enumerate(sets):
        assert np.array_equal(got[p], rp.predict([terms])[0])
    traj = rp.predict([base, kt, base], trajectory=True)
    for got_x, want_x in zip(traj, rp.predict([base, kt], trajectory=True)):
        assert np.array_equal(got_x, want_x[[0, 1, 0]])
    # the scans' mean losses, each distinct set predicted once
    rp.set_scales(rp.residuals([base])[0])
    w = np.flatnonzero(rp.active)
    each = [mean_losses(rp, [terms], w)[0] for terms in sets]
    assert np.array_equal(mean_losses(rp, sets, w), np.array(each))


def test_a_repeated_rejected_step_is_not_predicted_again(record, monkeypatch):
    """At convergence a fit tries nearly the same step several times over while its damping
    grows: a step within ``REPEAT_STEP`` of one just rejected by more than ``REPEAT_MARGIN``
    counts as rejected without a prediction, and the fit takes the same path."""
    from krang_discrepancy import fitting

    _, rp, base, effs, lo, hi, x, wsets = slope_and_kt_fit(
        record, ReplayConfig(stride_s=0.1, workers=1)
    )
    jobs = {}
    for margin in (np.inf, 1e-6):  # never a repeat; every near-repeat rejected by a margin
        monkeypatch.setattr(fitting, 'REPEAT_MARGIN', margin)
        job = FitJob(list(effs), 0, x.copy(), lo, hi, fd_steps(effs, x, lo, hi))
        batched_fit(rp, base, [job], wsets)
        jobs[margin] = job
    every, skipping = jobs[np.inf], jobs[1e-6]
    assert np.array_equal(skipping.x, every.x)
    assert skipping.iters == every.iters
    assert skipping.nfev < every.nfev
