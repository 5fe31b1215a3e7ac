"""The `krang discrepancy --json` object: the named effect(s) with value, unit and uncertainty,
the gap before and after, and the verdict (an ``unexplained`` answer keeps the fitted library
effects as ``partial``)."""

from __future__ import annotations

from .extended_model import effect_entries


def contract(result, gaps_yaml, base) -> dict:
    """The `krang discrepancy --json` object: effect, value, unit, uncertainty, gap_before,
    gap_after (or ``effects``, a list of those, for a combination), plus gap_unit, the physical
    pitch and wheel-angle gaps, detail (link / joint of a variant), heldout_improvement."""
    b, a = gaps_yaml['before'], gaps_yaml['after']
    g0, g1 = b['gap'], a['gap']
    extra = {
        'gap_unit': "RMS whitened error (1 = the nominal model's typical error per signal)",
        'gap_pitch_rad': [b['rms_q_base'], a['rms_q_base']],
        'gap_wheel_rad': [b['rms_wheel'], a['rms_wheel']],
    }
    if 'gap_matched' in a:  # judged against a baseline: the figure its verdict uses
        extra['gap_matched'] = [b['gap_matched'], a['gap_matched']]
    if result.selected is None:
        return {
            'effect': 'none',
            'value': None,
            'unit': None,
            'uncertainty': None,
            'gap_before': g0,
            'gap_after': g0,
            **extra,
            'gap_pitch_rad': [b['rms_q_base'], b['rms_q_base']],
            'gap_wheel_rad': [b['rms_wheel'], b['rms_wheel']],
            'best_candidate': result.singles[0].key if result.singles else None,
            'best_heldout_improvement': result.singles[0].improvement if result.singles else None,
        }
    entries = effect_entries(result.selected, base)
    if len(entries) == 1:
        e = entries[0]
        out = {
            'effect': e['effect'],
            'value': e['value'],
            'unit': e['unit'],
            'uncertainty': e['uncertainty'],
            'gap_before': g0,
            'gap_after': g1,
            **extra,
        }
        if 'detail' in e:
            out['detail'] = e['detail']
        out['heldout_improvement'] = result.selected.improvement
        out['at_bound'] = result.selected.at_bound
        return out
    items = []
    for k, e in enumerate(entries):
        item = {
            'effect': e['effect'],
            'value': e['value'],
            'unit': e['unit'],
            'uncertainty': e['uncertainty'],
            'gap_before': g0,
            'gap_after': gaps_yaml['steps'][k],
        }
        if 'detail' in e:
            item['detail'] = e['detail']
        items.append(item)
    return {
        'effects': items,
        'gap_before': g0,
        'gap_after': g1,
        **extra,
        'at_bound': result.selected.at_bound,
        'heldout_improvement': getattr(
            result.selected, 'improvement_vs_nominal', result.selected.improvement
        ),
    }


def with_verdict(js, verdict, reason, structure, result, base):
    """The JSON with the verdict: 'unexplained' replaces the name (the library effects that were
    fitted are kept as 'partial', with the share they explain)."""
    js = dict(js)
    js['signature'] = structure.as_dict()
    if verdict != 'unexplained':
        return js
    partial = js.get('effects') or (
        [{k: js[k] for k in ('effect', 'value', 'unit', 'uncertainty')}]
        if js.get('effect') not in (None, 'none')
        else []
    )
    out = {
        'effect': 'unexplained',
        'value': None,
        'unit': None,
        'uncertainty': None,
        'gap_before': js['gap_before'],
        'gap_after': js['gap_after'],
        'reason': reason,
        'partial': partial,
        'partial_heldout_improvement': (
            None if result.selected is None else result.selected.improvement
        ),
    }
    for k, v in js.items():
        if k not in out and k not in ('effect', 'effects', 'value', 'unit', 'uncertainty'):
            out[k] = v
    return out
