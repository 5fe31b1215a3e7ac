"""Hidden true robots for tests and demos: plausible perturbations of the nominal mass model whose
forward CoM error (as `krang demo` measures it) lies in a chosen range.

The recipe is the demo truth's (config/sim_demo_true_beta.yaml, `perturbed_beta`): masses
scaled within +-mass_fraction, then rescaled so the total mass is kept; every body's local CoM
moved by up to com_shift_m per axis; wheel CoMs centred on the axle. A draw is kept only if the
nominal model's forward CoM error against it (krang_model.com.com_error over the demo's held-out
configurations) lies in error_range_m; the seed then walks on (rejection sampling), so one seed
gives one truth.
"""

from dataclasses import asdict, dataclass

import numpy as np

from krang_bag.session_report import held_out_configurations
from krang_model.com import com_error



def perturbed_beta(robot, seed, mass_fraction=0.05, com_shift_m=0.03):
    """A physically plausible 'true' robot near the nominal one: masses within a few per cent,
    local CoMs moved by up to a few centimetres, total mass kept; wheels stay centred on their
    axle."""
    rng = np.random.default_rng(seed)
    b = robot.nominal_beta.reshape(-1, 4).copy()
    masses = b[:, 0] * (1.0 + rng.uniform(-mass_fraction, mass_fraction, len(b)))
    masses *= robot.nominal_mass / masses.sum()
    coms = np.divide(b[:, 1:], b[:, :1], out=np.zeros_like(b[:, 1:]), where=b[:, :1] != 0)
    coms += rng.uniform(-com_shift_m, com_shift_m, coms.shape)
    coms[robot.wheel_body_ids] = 0.0
    return np.column_stack([masses, masses[:, None] * coms]).ravel()


@dataclass(frozen=True)
class TruthRecipe:
    """How a hidden truth is drawn (see the module docstring)."""

    mass_fraction: float = 0.08
    com_shift_m: float = 0.03
    error_range_m: tuple = (0.012, 0.025)
    n_configs: int = 2000  # held-out configurations of the error (the demo's 2000)
    max_draws: int = 10000


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
        beta = perturbed_beta(
            robot, np.random.default_rng(s), recipe.mass_fraction, recipe.com_shift_m
        )
        err = com_error(robot, beta0, beta, joints)
        if lo <= err <= hi:
            return Truth(beta, int(seed), draw, err, recipe)
    raise RuntimeError(
        f'no truth with a forward error in [{lo}, {hi}] m within '
        f'{recipe.max_draws} draws of {recipe}'
    )
