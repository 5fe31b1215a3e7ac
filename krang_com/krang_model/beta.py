"""Beta files: the authors' text format (one 4B-vector per line) and our labelled YAML/JSON."""

import io
import json
from pathlib import Path

import numpy as np
import yaml

from .files import write_text


class BetaFileError(ValueError):
    """A beta file that cannot be read as the robot's parameter vector."""


def load_beta(path, robot, row=None):
    """One beta vector from a .txt (the authors' rows; `row` picks line K from 0, default 0), .yaml
    or .json file; validated against the robot."""
    path = Path(path)
    if not path.exists():
        raise BetaFileError(f'{path}: no such beta file')
    try:
        text = path.read_text()
    except OSError as err:
        raise BetaFileError(f'{path}: cannot read the beta file ({err.strerror})') from None
    except UnicodeDecodeError:
        raise BetaFileError(f'{path}: not a text file') from None
    if path.suffix in ('.yaml', '.yml', '.json'):
        try:
            doc = json.loads(text) if path.suffix == '.json' else yaml.safe_load(text)
        except (yaml.YAMLError, ValueError) as err:
            raise BetaFileError(f'{path}: not valid {_syntax_problem(err)}') from None
        beta = _from_labelled(doc, robot, path)
    else:
        try:
            rows = np.atleast_2d(np.loadtxt(io.StringIO(text), ndmin=2))
        except ValueError as err:
            raise BetaFileError(
                f'{path}: not a whitespace-separated numeric file ({err})'
            ) from None
        k = 0 if row is None else int(row)
        if not 0 <= k < rows.shape[0]:
            raise BetaFileError(
                f'{path}: --row {k} out of range, the file has {rows.shape[0]} rows'
            )
        beta = rows[k]
    beta = np.asarray(beta, dtype=float)
    if beta.shape != (robot.n_beta,):
        raise BetaFileError(
            f'{path}: {beta.size} numbers per beta, {robot.name} needs {robot.n_beta} '
            f'(4 per body x {robot.n_bodies} bodies)'
        )
    if not np.all(np.isfinite(beta)):
        raise BetaFileError(f'{path}: beta contains NaN or inf')
    return beta


def _syntax_problem(err):
    """'YAML (what, line L)' or 'JSON (what)' of a parser's error, on one line."""
    mark = getattr(err, 'problem_mark', None)
    if isinstance(err, yaml.YAMLError):
        where = f', line {mark.line + 1}' if mark is not None else ''
        return f'YAML ({getattr(err, "problem", None) or "syntax error"}{where})'
    return f'JSON ({err})'


def _from_labelled(doc, robot, path):
    if not isinstance(doc, dict) or not isinstance(doc.get('bodies'), list):
        raise BetaFileError(f'{path}: not a beta file: expected a mapping with a "bodies" list')
    bodies = [b for b in doc['bodies'] if isinstance(b, dict) and isinstance(b.get('name'), str)]
    by_name = {b['name']: b for b in bodies}
    missing = [b for b in robot.body_names if b not in by_name]
    if missing:
        raise BetaFileError(f'{path}: bodies missing: {missing}')
    beta = []
    for name in robot.body_names:
        b = by_name[name]
        try:
            beta += [float(b['m']), *(float(v) for v in b['m_com'])]
        except (KeyError, TypeError, ValueError) as err:
            raise BetaFileError(f'{path}: body {name}: needs m and m_com [3] ({err})') from None
    return beta


def beta_document(beta, robot, **meta):
    """A labelled, human-readable beta: mass, mass moment and CoM per body."""
    beta = np.asarray(beta, dtype=float)
    bodies = []
    for i, name in enumerate(robot.body_names):
        m, *mc = beta[4 * i : 4 * i + 4]
        com = [v / m for v in mc] if m != 0 else [None] * 3
        bodies.append(
            {
                'name': name,
                'm': float(m),
                'm_com': [float(v) for v in mc],
                'com': [None if v is None else float(v) for v in com],
            }
        )
    doc = {
        'robot': robot.name,
        'layout': '[m, m*x, m*y, m*z] per body, CoM in the body frame (kg, kg*m)',
        'total_mass': float(beta[0::4].sum()),
    }
    doc.update(meta)
    doc['bodies'] = bodies
    return doc


def save_beta(path, beta, robot, **meta):
    """Write beta: .txt = the authors' one-line format, .json = JSON, anything else = YAML."""
    path = Path(path)
    beta = np.asarray(beta, dtype=float)
    if path.suffix == '.txt':
        text = ' '.join(f'{v:.9g}' for v in beta) + '\n'
    elif path.suffix == '.json':
        text = json.dumps(beta_document(beta, robot, **meta), indent=1)
    else:
        text = yaml.safe_dump(beta_document(beta, robot, **meta), sort_keys=False)
    return write_text(path, text)
