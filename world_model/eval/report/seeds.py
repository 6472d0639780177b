"""One model row under several noise seeds: every score is the mean over the seeds, with its spread."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from world_model.eval.report.results import RowScores, RowSpread


def average_seeds(results: Sequence[RowScores]) -> RowScores:
    """One row from its scores under several noise seeds: every score is the mean over seeds;
    ``seeds`` holds their count and ``spread`` the standard deviation of Table 1, Table 2, the
    per-view scores, the scene IoU and what a policy reads. A score missing (None) in any seed is
    None, not the mean of the others."""
    if not results:
        raise ValueError("average_seeds needs at least one seeded result")
    spread = RowSpread(
        table1=leaf_mean([r.table1 for r in results], spread=True),
        table2=leaf_mean([r.table2 for r in results], spread=True),
        per_view=leaf_mean([r.per_view for r in results], spread=True),
        scene_iou=leaf_mean([r.scene_iou for r in results], spread=True),
        decisions=leaf_mean([r.decisions for r in results], spread=True),
    )
    return replace(leaf_mean(list(results), spread=False), seeds=len(results), spread=spread)


def leaf_mean(values: Sequence[Any], spread: bool) -> Any:
    """Number-by-number mean (``spread``: standard deviation) of equally shaped values: frozen
    dataclasses field by field, mappings with the same keys key by key, tuples of one length item
    by item. A number missing (None) in any value is None; a count that every value agrees on
    stays that count; other leaves (names, mismatched shapes) are the first value's (no spread)."""
    first = values[0]
    if dataclasses.is_dataclass(first) and all(type(v) is type(first) for v in values):
        return type(first)(**{f.name: leaf_mean([getattr(v, f.name) for v in values], spread)
                              for f in dataclasses.fields(first)})  # fmt: skip
    if isinstance(first, Mapping) and all(isinstance(v, Mapping) and v.keys() == first.keys() for v in values):
        return {k: leaf_mean([v[k] for v in values], spread) for k in first}
    if isinstance(first, tuple) and all(isinstance(v, tuple) and len(v) == len(first) for v in values):
        return tuple(leaf_mean([v[i] for v in values], spread) for i in range(len(first)))
    if all(_is_number(v) for v in values):
        if not spread and all(isinstance(v, int) and v == first for v in values):
            return first  # a count (answers, seconds) the seeds share
        return float(np.std(values)) if spread else float(np.mean(values))
    if all(v is None or _is_number(v) for v in values) and any(v is None for v in values):
        return None
    return None if spread else first


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)
