"""The nominal model the measured data are compared with."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from krang_model.beta import load_beta
from krang_model.config import config_path
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang

from krang_model.effects import ModelTerms


@dataclass
class NominalModel:
    """The model the data are compared with: robot (pinocchio), mass model beta, drive train."""

    robot: object
    beta: np.ndarray
    drive: object
    beta_source: str = ''

    @classmethod
    def default(cls, beta_path=None, **drive_overrides) -> 'NominalModel':
        """Krang with config/sim_true_beta.yaml (the physically consistent fit to the real
        balanced poses: the project's best mass model) and the drive train of config/robot.yaml."""
        robot = load_krang()
        path = Path(beta_path) if beta_path else Path(config_path('sim_true_beta.yaml'))
        return cls(robot, load_beta(path, robot), drivetrain(robot, **drive_overrides), str(path))

    def terms(self) -> ModelTerms:
        return ModelTerms.nominal(self.drive)
