"""Hidden true robots for tests, demos and experiments: plausible perturbations of the nominal mass
model whose forward CoM error lies in a chosen range. The one recipe (`perturbed_betas`):

masses scaled within +-mass_fraction, then brought back to the nominal total mass (rescaled, or
the difference put on one body); every body's local CoM moved by up to com_shift_m per axis;
wheel CoMs centred on the axle (and, optionally, both wheels of one mass); optionally some bodies
kept as they are. The demo truth (config/sim_demo_true_beta.yaml) is `perturbed_beta`. A draw is
kept only if the start model's forward CoM error against it lies in error_range_m:
`generate_truth` gives one truth per seed (krang_model.com.com_error over the demo's held-out
configurations; the seed walks on, so one seed gives one truth), `generate_truths` many from one
generator, in batches (krang_model.com.PoseMoments over given configurations).
"""

from dataclasses import asdict, dataclass

import numpy as np

from krang_bag.session_report import held_out_configurations
from krang_model.com import com_error


def perturbed_betas(
    robot,
    rng,
    count,
    mass_fraction=0.05,
    com_shift_m=0.03,
    total_mass_on=None,
    keep_bodies=(),
    equal_wheels=False,
):
    """`count` draws of the recipe from the generator `rng` (count, n_beta): all masses first, then
    all CoM shifts. The total mass stays the nominal one by rescaling every mass, or, with
    total_mass_on (a body name), by putting the difference on that body. keep_bodies (names) keep
    their nominal mass and CoM; equal_wheels gives the right wheel the left one's mass."""
    b = robot.nominal_beta.reshape(-1, 4)
    m0 = b[:, 0]
    c0 = np.divide(b[:, 1:], b[:, :1], out=np.zeros_like(b[:, 1:]), where=b[:, :1] != 0)
    masses = m0 * (1.0 + rng.uniform(-mass_fraction, mass_fraction, (count, len(b))))
    coms = c0 + rng.uniform(-com_shift_m, com_shift_m, (count, len(b), 3))
    keep = [robot.body_names.index(name) for name in keep_bodies]
    masses[:, keep] = m0[keep]
    coms[:, keep] = c0[keep]
    wheels = robot.wheel_body_ids
    if equal_wheels:
        masses[:, wheels[1]] = masses[:, wheels[0]]
    coms[:, wheels] = 0.0
    if total_mass_on is None:
        masses *= (robot.nominal_mass / masses.sum(1))[:, None]
    else:
        masses[:, robot.body_names.index(total_mass_on)] += robot.nominal_mass - masses.sum(1)
    return np.concatenate([masses[..., None], masses[..., None] * coms], axis=2).reshape(count, -1)


def perturbed_beta(robot, seed, mass_fraction=0.05, com_shift_m=0.03):
    """One draw of the recipe from `seed` (an int or a Generator): masses within a few per cent,
    rescaled to the nominal total, local CoMs moved by up to a few centimetres, wheels centred."""
    rng = np.random.default_rng(seed)
    return perturbed_betas(robot, rng, 1, mass_fraction, com_shift_m)[0]


@dataclass(frozen=True)
class TruthRecipe:
    """How a hidden truth is drawn (see the module docstring)."""

    mass_fraction: float = 0.08
    com_shift_m: float = 0.03
    error_range_m: tuple = (0.012, 0.025)
    n_configs: int = 2000  # held-out configurations of the error (the demo's 2000)
    max_draws: int = 10000
    total_mass_on: str | None = None  # None: rescale every mass; else the body that takes it
    keep_bodies: tuple = ()
    equal_wheels: bool = False


@dataclass(frozen=True)
class Truth:
    beta: np.ndarray
    seed: int  # the caller's seed
    draw: int  # draws rejected before this one
    forward_error_m: float  # of the start model (beta0) against this truth
    recipe: TruthRecipe

    def describe(self):
        return (
            f'generated truth (seed {self.seed}, draw {self.draw}; masses within '
            f'{100 * self.recipe.mass_fraction:.0f} %, CoMs moved up to '
            f'{100 * self.recipe.com_shift_m:.1f} cm; forward error '
            f'{1000 * self.forward_error_m:.1f} mm)'
        )

    def meta(self):
        """For the beta file's header (krang_model.beta.save_beta)."""
        return {
            'source': self.describe(),
            'recipe': asdict(self.recipe),
            'seed': self.seed,
            'forward_error_m': self.forward_error_m,
        }


def generate_truth(robot, seed, recipe=None, beta0=None):
    """The first draw of the recipe, from `seed`, whose forward CoM error against `beta0` (default:
    the nominal model) lies in recipe.error_range_m."""
    recipe = recipe or TruthRecipe()
    beta0 = robot.nominal_beta if beta0 is None else np.asarray(beta0, dtype=float)
    joints = held_out_configurations(robot, recipe.n_configs)
    lo, hi = recipe.error_range_m
    seeds = np.random.SeedSequence(seed).spawn(recipe.max_draws)
    for draw, s in enumerate(seeds):
        beta = _draw(robot, np.random.default_rng(s), 1, recipe)[0]
        err = com_error(robot, beta0, beta, joints)
        if lo <= err <= hi:
            return Truth(beta, int(seed), draw, err, recipe)
    raise RuntimeError(
        f'no truth with a forward error in [{lo}, {hi}] m within '
        f'{recipe.max_draws} draws of {recipe}'
    )


def generate_truths(robot, n, rng, recipe, moments, beta0=None, max_rounds=200):
    """n draws of the recipe from the generator `rng`, in batches of 4n, kept when beta0's
    (default: the nominal model) mean balance error (krang_model.com.PoseMoments.errors over the
    configurations of `moments`) lies in recipe.error_range_m. (n, n_beta)."""
    beta0 = robot.nominal_beta if beta0 is None else np.asarray(beta0, dtype=float)
    lo, hi = recipe.error_range_m
    out = []
    for _ in range(max_rounds):
        k = 4 * n
        T = _draw(robot, rng, k, recipe)
        bal, _ = moments.errors(np.repeat(beta0[None], k, 0), T)
        T = T[(bal >= lo) & (bal <= hi)]
        out.append(T)
        if sum(len(t) for t in out) >= n:
            return np.concatenate(out)[:n]
    raise RuntimeError(f'could not draw {n} truths of {recipe} in {max_rounds} rounds')


def _draw(robot, rng, count, recipe):
    return perturbed_betas(
        robot,
        rng,
        count,
        recipe.mass_fraction,
        recipe.com_shift_m,
        recipe.total_mass_on,
        recipe.keep_bodies,
        recipe.equal_wheels,
    )
