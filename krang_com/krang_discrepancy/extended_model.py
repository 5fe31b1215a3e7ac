"""The extended-model file, DIR/extended_model.yaml: the nominal model a run of `krang discrepancy`
compared the data with, the effects it named (value, unit, uncertainty and the fitted parameter
of each, in the vocabulary of ``krang_model.effects``), the data, the gap and the yardstick of
later runs. ``load_extended_model`` gives the ``ModelTerms`` of the robot it describes: what a
plant is built with (``krang_sim.plant``, ``terms=``) and what a later run is judged against
(``--baseline``)."""

from __future__ import annotations

import numpy as np
import yaml

from krang_model.effects import ModelTerms, model_terms
from krang_model.files import atomic_open

from .nominal import NominalModel

FORMAT = 'krang_discrepancy/extended_model/1'


def effect_entries(fit, base: ModelTerms) -> list:
    """One dict per effect of a fit: name, key, value (reported units, physical: a torque
    constant in N m/A of the robot with `base`'s Kt times the fitted scale), parameter,
    uncertainty."""
    out = []
    if fit is None:
        return out
    for e, v, u in zip(fit.effects, fit.values, fit.uncertainty):
        dv, unit = e.display(float(v), base)
        out.append(
            {
                'effect': e.name,
                'key': e.key,
                'value': float(dv),
                'unit': unit,
                'uncertainty': float(u) * e.display_scale(base),
                'parameter': float(v),
                **({'detail': e.detail} if e.detail else {}),
            }
        )
    return out


def write_extended_model(
    path, fit, model: NominalModel, *, sources=(), gaps=None, base=None, baseline=None, extra=None
) -> dict:
    """The extended model as YAML: the nominal model it extends and the effects (value, unit,
    uncertainty, fitted parameter; ``load_extended_model`` applies the parameters in order).

    With ``baseline`` (the document of an earlier extended model, whose terms are `base`) the file
    is complete: the baseline's effects first (marked with the file they came from), then the new
    ones, so that it can serve as the next baseline (the effects apply in order)."""
    base = model.terms() if base is None else base
    new = effect_entries(fit, base)
    old = [
        dict(e, **({} if 'from' in e else {'from': baseline.get('path', '')}))
        for e in (baseline or {}).get('effects', [])
    ]
    entries = old + new
    doc = {
        'format': FORMAT,
        'nominal': {
            'beta': model.beta_source,
            'wheel_radius_m': float(model.drive.wheel_radius),
            'torque_constant_Nm_per_A': float(model.drive.torque_constant),
            'viscous_friction_Nm_s': float(model.drive.viscous_friction),
            'coulomb_friction_Nm': float(model.drive.coulomb_friction),
            'floor_slope_rad': float(model.drive.floor_slope),
        },
        'effects': [{k: v for k, v in ent.items()} for ent in entries],
        'data': [str(s) for s in sources],
    }
    if baseline:
        doc['baseline'] = baseline.get('path', '')
    if extra:
        doc.update(extra)
    if gaps:
        doc['gap'] = gaps
    with atomic_open(path, 'w') as f:
        f.write(
            '# Extended Krang model found by `krang discrepancy`: the effects of '
            'krang_model.effects,\n# applied in order at their `parameter` on the nominal model.\n'
        )
        yaml.safe_dump(plain(doc), f, sort_keys=False)
    return doc


def plain(o):
    """`o` with numpy scalars as Python numbers and tuples as lists (for YAML and JSON)."""
    if isinstance(o, dict):
        return {str(k): plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [plain(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    return o


def load_extended_model(path, base: ModelTerms | None = None) -> ModelTerms:
    """The ``ModelTerms`` of an extended-model YAML: every listed effect (by key, from the
    registry) at its fitted parameter, in order, on top of `base` (default: the nominal model the
    file names). The effects list is the whole model: other sections a file may hold (a
    ``sim_effects`` mapping, say) are not read."""
    with open(path) as f:
        doc = yaml.safe_load(f)
    if not isinstance(doc, dict) or doc.get('format') != FORMAT:
        raise ValueError(f'{path}: not an extended-model file ({FORMAT})')
    if base is None:
        base = NominalModel.default((doc.get('nominal') or {}).get('beta') or None).terms()
    entries = doc.get('effects') or []
    return model_terms([(e['key'], e['parameter']) for e in entries], base)
