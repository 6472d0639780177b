"""Table 2's questions: what the judge is asked about a row's frames of one clip, and the
yes-frequencies (per question, per object category, per camera view) of its answers."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from world_model.data import Clip
from world_model.eval.crops import CropConfig, ObjectCrop, extract_crops, group_by_track_time
from world_model.eval.judge import JudgeBackend
from world_model.eval.questions import QUESTION_TYPES
from world_model.eval.report.config import ReportConfig
from world_model.eval.report.results import PerView, YesFrequencies
from world_model.sim import ProceduralSimulator


@dataclass(frozen=True)
class Answer:
    """One yes/no answer of the judge."""

    question: str
    yes: bool
    category: str | None  # the asked-about object's category; None for scene questions
    view: int | None = None  # the camera a scene question was asked about; None for object questions


def judge_scene_per_view(backend: JudgeBackend, frames: np.ndarray, weather: str, time_of_day: str) -> list[Answer]:
    """Weather and time of day asked of every view of ``frames`` (N, V, H, W, 3) on its own, so a
    frame whose views disagree (some dark as night) cannot pass as one averaged scene."""
    n, v = frames.shape[:2]
    views = frames.reshape(n * v, 1, *frames.shape[2:])
    view_of = np.tile(np.arange(v), n).tolist()
    weathers = backend.is_weather(views, [weather] * len(views))
    answers = [Answer("weather", bool(y), None, k) for y, k in zip(weathers, view_of, strict=True)]
    times = backend.is_time_of_day(views, [time_of_day] * len(views))
    return answers + [Answer("time_of_day", bool(y), None, k) for y, k in zip(times, view_of, strict=True)]


def per_view(answers: Sequence[Answer]) -> PerView:
    """Yes-frequency of each scene question per camera view: {question: (view 0, view 1, ...)}."""
    out: dict[str, tuple[float | None, ...]] = {}
    for q in ("weather", "time_of_day"):
        scored = [a for a in answers if a.question == q and a.view is not None]
        if not scored:
            continue
        views = max(a.view for a in scored) + 1
        out[q] = tuple(
            float(np.mean(ys)) if (ys := [a.yes for a in scored if a.view == k]) else None for k in range(views)
        )
    return out


def judge_clip(
    backend: JudgeBackend, clip: Clip, cameras: np.ndarray, sim: ProceduralSimulator, config: ReportConfig,
    crop_config: CropConfig,
) -> list[Answer]:  # fmt: skip
    """Ask every question of Table 2 about ``cameras`` (T, V, H, W, 3), the row's frames of ``clip``."""
    idx = list(range(0, clip.num_frames, config.frame_stride))
    prompt = clip.frames[0].prompt
    frames = np.ascontiguousarray(cameras[idx])
    answers = judge_scene_per_view(backend, frames, prompt.weather, prompt.time_of_day)
    crops: list[ObjectCrop] = []
    for i in idx:
        crops += extract_crops(clip.frames[i], np.ascontiguousarray(cameras[i]), sim, crop_config)
    if not crops:
        return answers
    images, cats = [c.image for c in crops], [c.category for c in crops]
    answers += [Answer("existence", bool(y), c) for y, c in zip(backend.is_category(images, cats), cats, strict=True)]
    answers += [Answer("clarity", bool(y), c) for y, c in zip(backend.is_clear(images), cats, strict=True)]
    ref = [c for c in crops if c.track_id in clip.crops]
    if ref:
        same = backend.same_object([c.image for c in ref], [clip.crops[c.track_id] for c in ref])
        answers += [Answer("visual_fidelity", bool(y), c.category) for y, c in zip(same, ref, strict=True)]
    text = [c for c in crops if backend.understands(c.description)]
    if text:
        match = backend.matches_description([c.image for c in text], [c.description for c in text])
        answers += [Answer("textual_fidelity", bool(y), c.category) for y, c in zip(match, text, strict=True)]
    pairs = [(g[k], g[k + 1]) for g in group_by_track_time(crops).values() for k in range(len(g) - 1)]
    if pairs:
        ok = backend.consistent([a.image for a, _ in pairs], [b.image for _, b in pairs])
        answers += [Answer("cross_view_consistency", bool(y), a.category) for y, (a, _) in zip(ok, pairs, strict=True)]
    return answers


def yes_frequencies(answers: Sequence[Answer]) -> YesFrequencies:
    """Fraction of yes per question type (None where the question was never asked)."""
    out: dict[str, float | None] = {}
    for q in QUESTION_TYPES:
        ys = [a.yes for a in answers if a.question == q]
        out[q] = float(np.mean(ys)) if ys else None
    return YesFrequencies(**out)


def per_category(answers: Sequence[Answer]) -> dict[str, dict[str, float]]:
    """Yes-frequency per object question and category: {question: {category: frequency}}."""
    groups: dict[str, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    for a in answers:
        if a.category is not None:
            groups[a.question][a.category].append(a.yes)
    return {q: {c: float(np.mean(v)) for c, v in sorted(d.items())} for q, d in groups.items()}
