"""The learning library: the mass model beta from balanced poses (pure numpy; no rclpy).

Modules of one job each: rows (the measurement model), priors (prior spread and physical
constraints), solvers (the MAP solvers and the evidence), registry (the estimator protocol and
registry), estimators (the built-in estimators: the paper's GD and the MAP family), crossval
(k-fold cross-validation). Their public names are importable from the package itself.
"""

from .crossval import cross_validate, cross_validate_fit, fold_split
from .estimators import (
    MAP,
    MAPEstimator,
    MAPOnline,
    PaperGD,
    PaperGDMass,
    RowUpdates,
    gd_step,
    gd_stop_count,
    mass_weights,
    project_total_mass,
)
from .priors import (
    COM_RADIUS_M,
    MASS_SPREAD,
    com_balls,
    com_bounds,
    com_shift_std,
    equality_constraints,
    inequality_constraints,
    mass_bounds,
    physical_consistency,
    physical_prior_std,
    recipe_prior_std,
)
from .registry import (
    ENTRY_POINT_GROUP,
    ESTIMATORS,
    Estimator,
    estimator_names,
    make_estimator,
    register_estimator,
)
from .rows import (
    NoiseModel,
    angle_rows,
    balanced_pose_rows,
    offset_rows,
    pitch_rows,
    pitch_sensitivity,
)
from .solvers import (
    CALIBRATION_BOUNDS,
    calibrate_scales,
    condition_on_constraints,
    log_evidence,
    map_batch,
    map_constrained,
    map_gauss_newton,
    map_gauss_newton_rows,
    null_space,
    within_bounds,
)

__all__ = [
    'CALIBRATION_BOUNDS',
    'COM_RADIUS_M',
    'MASS_SPREAD',
    'ENTRY_POINT_GROUP',
    'ESTIMATORS',
    'MAP',
    'MAPEstimator',
    'MAPOnline',
    'NoiseModel',
    'PaperGD',
    'PaperGDMass',
    'RowUpdates',
    'Estimator',
    'angle_rows',
    'balanced_pose_rows',
    'calibrate_scales',
    'com_balls',
    'com_bounds',
    'com_shift_std',
    'condition_on_constraints',
    'cross_validate',
    'cross_validate_fit',
    'equality_constraints',
    'estimator_names',
    'fold_split',
    'gd_step',
    'gd_stop_count',
    'inequality_constraints',
    'log_evidence',
    'make_estimator',
    'mass_bounds',
    'mass_weights',
    'map_batch',
    'map_constrained',
    'map_gauss_newton',
    'map_gauss_newton_rows',
    'null_space',
    'within_bounds',
    'offset_rows',
    'physical_consistency',
    'physical_prior_std',
    'pitch_rows',
    'pitch_sensitivity',
    'project_total_mass',
    'recipe_prior_std',
    'register_estimator',
]
