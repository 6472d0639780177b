"""Score rows on clips (:func:`evaluate_rows` -> :class:`Report`) and write report.md / report.json."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path

from world_model.data import Clip
from world_model.eval.judge import JudgeBackend, load_default_judge
from world_model.eval.report.cache import RowCache, row_cache_key
from world_model.eval.report.clip_scores import ClipScores, ClipTruth, clip_truth, score_clip
from world_model.eval.report.config import ReportConfig
from world_model.eval.report.markdown import format_markdown
from world_model.eval.report.results import Report, RowScores
from world_model.eval.report.row_scores import row_scores
from world_model.eval.report.rows import RowFn, check_generated
from world_model.eval.report.seeds import average_seeds
from world_model.eval.segmenter import Segmenter, load_default_segmenter
from world_model.sim import ProceduralSimulator

log = logging.getLogger(__name__)


def evaluate_rows(
    rows: dict[str, RowFn | Sequence[RowFn]],
    clips: Sequence[Clip],
    judge: JudgeBackend | None = None,
    config: ReportConfig | None = None,
    cache_dir: str | Path | None = None,
    row_ids: dict[str, str] | None = None,
    segmenter: Segmenter | None = None,
) -> Report:
    """Score every row on every clip.

    ``config``: the sampling (default :class:`ReportConfig`). ``judge`` answers the questions
    (default: the shipped CNN judge); its ``frame_features`` feed the Fréchet distances (a backend
    without them gets None there). ``segmenter`` labels the rows' camera pixels for the scene IoU
    against the recordings' label maps, and the rows' and the recordings' FRONT views for what a
    policy reads (default: the shipped one). A row given as a sequence of
    generators is one model under several noise seeds: each is scored and the row holds their mean
    (:func:`~world_model.eval.report.seeds.average_seeds`).

    Rows take minutes to hours, so with ``cache_dir`` each finished row is written there
    (``<row>.json``, or ``<row>.seed<k>.json`` per seed) under a key made of ``row_ids[row]`` and
    what else its scores depend on (:mod:`~world_model.eval.report.cache`); a later call with the
    same key reuses it instead of generating again. Rows without an id are never cached.
    """
    if not rows or not clips:
        raise ValueError("evaluate_rows needs at least one row and one clip")
    judge = judge if judge is not None else load_default_judge()
    segmenter = segmenter if segmenter is not None else load_default_segmenter()
    config = config if config is not None else ReportConfig()
    truths = [clip_truth(c, judge, config, segmenter) for c in clips]
    cache = RowCache(Path(cache_dir)) if cache_dir is not None else None
    scored: dict[str, RowScores] = {}

    def cached(name: str, fn: RowFn, row_id: str | None) -> RowScores:
        keyed = cache is not None and row_id is not None
        key = row_cache_key(row_id, clips, config, judge, segmenter) if keyed else None
        if key is not None and (hit := cache.load(name, key)) is not None:
            return hit
        t0 = time.perf_counter()
        log.info("report row %s: generating and scoring %d clips", name, len(clips))
        result = score_row(name, fn, clips, judge, segmenter, truths, config)
        log.info("report row %s: done in %.0f s", name, time.perf_counter() - t0)
        if key is not None:
            cache.save(name, key, row_id, result)
        return result

    for row, fns in rows.items():
        row_id = (row_ids or {}).get(row)
        if isinstance(fns, Sequence):  # one model under several noise seeds: scored each, then averaged
            seeded = [None if row_id is None else f"{row_id},noise_seed_index={k}" for k in range(len(fns))]
            scored[row] = average_seeds(
                [cached(f"{row}.seed{k}", fn, rid) for k, (fn, rid) in enumerate(zip(fns, seeded, strict=True))]
            )
        else:
            scored[row] = cached(row, fns, row_id)
    return Report(rows=scored, clips=tuple(c.name for c in clips), config=config)


def score_row(
    row: str,
    fn: RowFn,
    clips: Sequence[Clip],
    judge: JudgeBackend,
    segmenter: Segmenter,
    truths: Sequence[ClipTruth],
    config: ReportConfig,
) -> RowScores:
    """Generate ``row``'s sensors for every clip and score them against the clips' ``truths``
    (:func:`~world_model.eval.report.clip_scores.clip_truth`). A row that can generate every clip
    at once (``generate_all``: batched rollouts) does so up front; each clip is let go once scored."""
    sim = ProceduralSimulator()
    generated = fn.generate_all(clips) if hasattr(fn, "generate_all") else None
    per_clip: list[ClipScores] = []
    for i, clip in enumerate(clips):
        gen = generated[i] if generated is not None else fn(clip)
        if generated is not None:
            generated[i] = None
        check_generated(gen, clip, row)
        per_clip.append(score_clip(gen, clip, judge, segmenter, truths[i], config, sim))
    gt_features = [t.features for t in truths] if all(t.features is not None for t in truths) else []
    return row_scores(per_clip, config, gt_features)


def write_report(report: Report, out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``report.md`` and ``report.json`` into ``out_dir``; returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "report.md", out / "report.json"
    md.write_text(format_markdown(report))
    js.write_text(json.dumps(report.to_json(), indent=1))
    return md, js
