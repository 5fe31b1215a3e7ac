"""The replay's fast path is the model's one statement of the equations and its one integrator.

``krang_model.wip_batch.integrate`` steps the replay's batches with the model's functions compiled
(the CoM angle's sine and cosine carried by rotation between exact anchors): a simulator's float
step to rounding. A prediction does not depend on how its windows are chunked or
on the threads that run the chunks, nor on the other parameter sets of its batch (a set asked for
twice is predicted once); the fits' Levenberg-Marquardt skips the Jacobian of a rejected step,
and the prediction of a step that repeats one it has just rejected, without changing its path.
"""

import hashlib
from dataclasses import replace
from pathlib import Path

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
from krang_model.drivetrain import drivetrain
from krang_model.effects import apply_effects, library, model_terms
from krang_model import wip
from krang_model.robot import load_krang
from krang_model.wip import WipBody, WipDynamics
from krang_model.wip_batch import drive_table, integrate, simd_tanh


def _batch(p=3, s=40, seed=0):
    """Drive trains (friction, slope, ground damping differ), per-window bodies, states around
    the balance and on the caster (-1.76 rad, so the contact acts in some) and torques."""
    rng = np.random.default_rng(seed)
    nominal = drivetrain(load_krang())
    drives = [
        replace(nominal, coulomb_friction=c, floor_slope=a, ground_viscous=g)
        for c, a, g in ((0.0, 0.0, 0.0), (2.0, 0.02, 0.0), (5.0, -0.01, 3.0))[:p]
    ]
    body = WipBody(
        mass=140.0,
        com_distance=rng.uniform(0.15, 0.3, s),
        com_offset=rng.normal(0.0, 0.05, s),
        inertia_axle=rng.uniform(15.0, 25.0, s),
    )
    qb = rng.uniform(-1.8, -1.45, (p, s))
    state = np.stack(
        [rng.normal(0, 1, (p, s)), qb, rng.normal(0, 2, (p, s)), rng.normal(0, 0.5, (p, s))], -1
    )
    return drives, body, state, rng.normal(0, 15, s)


def _integrate(drives, bodies, state, tau, steps, anchor, force=None, calls=1):
    """``integrate`` of `state` (P, S, 4) over `steps` sub-steps of 2 ms under the torque `tau`
    (S,), one body per stretch of steps (`bodies`: WipBody of (S,) fields each, the stretches
    equal), in `calls` calls: every sub-step's state (P, S, steps + 1, 4)."""
    p, s = state.shape[:2]
    per = steps // len(bodies)
    table = lambda f: np.repeat(np.stack([getattr(b, f) for b in bodies], -1)[None], per, axis=2)  # noqa: E731
    f = np.zeros((p, s)) if force is None else force
    rec = np.empty((p, s, steps + 1, 4))
    rec[:, :, 0] = state
    x, trig = state.copy(), np.zeros((p, s, 2))
    cuts = np.linspace(0, steps, calls + 1).astype(int)
    for j0, j1 in zip(cuts[:-1], cuts[1:]):
        integrate(
            x, trig, j0, j1, 2e-3, anchor, np.array([bodies[0].mass]),
            *(table('com_distance'), table('com_offset'), table('inertia_axle')),
            np.zeros(p, np.int64), np.repeat(tau[None, :, None], steps, axis=2),
            np.zeros(p, np.int64), np.ones(p), np.zeros(p), np.zeros(p), drive_table(drives),
            f, -f, np.arange(steps + 1), rec,
        )  # fmt: skip
    return rec


def _float_steps(drives, bodies, state, tau, steps, force=None):
    """The same sub-steps, element by element, with a simulator's float step (``step_pitch``)."""
    p, s = state.shape[:2]
    per = steps // len(bodies)
    out = np.empty((p, s, steps + 1, 4))
    touching = 0
    for k, d in enumerate(drives):
        for i in range(s):
            x = tuple(float(v) for v in state[k, i])
            out[k, i, 0] = x
            f = 0.0 if force is None else float(force[k, i])
            for j in range(steps):
                dyn = WipDynamics(bodies[j // per][i], d)
                touching += dyn.caster_torque(x[1], x[3]) > 0
                x = dyn.step_pitch(*x, float(tau[i]), 2e-3, f, -f)
                assert all(type(v) is float for v in x)
                out[k, i, j + 1] = x
    return out, touching


def test_the_compiled_loops_disk_cache_is_keyed_on_the_physics():
    """numba keys its on-disk cache on the loop's own file and on the cells of its closure: the
    hash of ``krang_model/wip.py`` must be one of them, or a change of the physics would reuse a
    stale compiled loop."""
    physics = hashlib.sha256(Path(wip.__file__).read_bytes()).hexdigest()
    cells = [c.cell_contents for c in integrate.py_func.__closure__ or ()]
    assert physics in cells


def test_the_compiled_tanh_is_tanh_to_a_few_ulp():
    """``simd_tanh`` (what the compiled equations run for ``smooth_sign``) against numpy's tanh:
    within 4 ulp relative everywhere, near zero and in saturation too, odd, and exactly +-1
    beyond saturation."""
    x = np.concatenate([np.linspace(-30, 30, 200_001), np.logspace(-300, 1.5, 5000)])
    x = np.concatenate([x, -x])
    want = np.tanh(x)
    got = simd_tanh(x)
    nonzero = want != 0
    ulp = np.abs(got - want)[nonzero] / (np.abs(want[nonzero]) * np.finfo(float).eps)
    assert ulp.max() <= 4
    assert np.array_equal(simd_tanh(-x), -got)
    assert simd_tanh(1e300) == 1.0 and simd_tanh(-1e300) == -1.0 and simd_tanh(0.0) == 0.0


@pytest.mark.parametrize('force', [False, True])
def test_the_compiled_batch_is_the_float_step_with_exact_trigonometry(force):
    """Element by element, the compiled batch and a simulator's float step run the one statement
    of the equations and the one integrator (friction, slope, ground damping, caster contact and
    extra forces included): equal to rounding with exact sines and cosines at every step."""
    drives, body, state, tau = _batch(s=12, seed=5)
    f = np.linspace(-2.0, 2.0, 12)[None] + np.zeros((3, 1)) if force else None
    want, touching = _float_steps(drives, [body], state, tau, 40, f)
    got = _integrate(drives, [body], state, tau, 40, anchor=1, force=f)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * (1 + np.abs(want).max()))
    assert touching > 0  # the caster's contact acted


def test_the_batch_carries_sines_and_cosines_to_rounding():
    drives, body, state, tau = _batch(seed=3)
    want = _integrate(drives, [body], state, tau, 150, anchor=1)
    got = _integrate(drives, [body], state, tau, 150, anchor=16)
    assert np.all(np.isfinite(want))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-11 * (1 + np.abs(want).max()))


def test_the_carried_sines_and_cosines_follow_a_body_change():
    """A new body mid-horizon (the replay's moving pose) turns the carried sines and cosines by
    the change of the CoM offset, and the batch agrees with float steps to rounding, in one call
    or in several (the replay's sub-step by sub-step calls when a set has extra forces)."""
    drives, body, state, tau = _batch(s=10, seed=6)
    moved = replace(body, com_offset=body.com_offset + 0.03, com_distance=body.com_distance * 0.9)
    want, _ = _float_steps(drives, [body, moved], state, tau, 140)  # the change between anchors
    tol = 1e-11 * (1 + np.abs(want).max())
    for calls in (1, 7, 140):
        got = _integrate(drives, [body, moved], state, tau, 140, anchor=16, calls=calls)
        np.testing.assert_allclose(got, want, rtol=0, atol=tol)


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
