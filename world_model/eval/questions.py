"""Yes/no question sets with known answers, built from ground-truth :class:`JudgeData`: they train
the thresholds of the CNN judge (calibration) and measure any :class:`JudgeBackend`'s accuracy.

Each question type gets positives (the true attribute / the same object) and as many negatives
(a wrong weather, time, category or colour; a degraded crop; another track's crop; another
object's description). Accuracy is reported as balanced accuracy (mean of the yes-rate on
positives and the no-rate on negatives), overall and per category of the asked-about object
(per camera view for weather and time of day, which are asked of each view on its own).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from world_model.eval.judge import JudgeBackend
from world_model.eval.judge_data import DegradeConfig, JudgeData, degrade
from world_model.eval.nets import BACKGROUND, COLOR_CLASSES, CROP_CLASSES
from world_model.eval.text import parse_description
from world_model.scene import CATEGORIES, TIMES_OF_DAY, WEATHERS

QUESTION_TYPES = (
    "weather",
    "time_of_day",
    "existence",
    "clarity",
    "visual_fidelity",
    "textual_fidelity",
    "cross_view_consistency",
)


@dataclass
class QuestionSet:
    """One question type: inputs (frames array, or crop lists), what is asked, the true answers."""

    a: list | np.ndarray
    label: np.ndarray  # bool (N,)
    group: list[str]  # category of the asked-about object (the camera view for scene questions)
    b: list | None = None  # second crop of pair questions
    asked: list[str] | None = None  # the weather / time / category / description asked about
    extra: dict = field(default_factory=dict)


def _pick_other(rng: np.random.Generator, options: tuple[str, ...], true: str) -> str:
    others = [o for o in options if o != true]
    return others[int(rng.integers(len(others)))]


@dataclass
class _Draw:
    """What every question type draws from: the crops and their arrays, the object crops (not the
    references), the one random stream (the types draw from it in a fixed order) and the cap of
    source items per type."""

    data: JudgeData
    arr: dict[str, np.ndarray]
    obj: np.ndarray
    rng: np.random.Generator
    max_per_type: int

    def sub(self, idx: np.ndarray) -> np.ndarray:
        """At most ``max_per_type`` of ``idx``, drawn at random, in order."""
        if len(idx) > self.max_per_type:
            return np.sort(self.rng.choice(idx, size=self.max_per_type, replace=False))
        return idx

    def cat(self, i: int) -> str:
        return CROP_CLASSES[self.arr["category"][i]]


def build_questions(
    data: JudgeData, seed: int = 0, max_per_type: int = 2000, degrade_config: DegradeConfig | None = None
) -> dict[str, QuestionSet]:
    """Question sets of every type in :data:`QUESTION_TYPES` plus ``"color"`` (calibration only).
    Deterministic in ``seed``; at most ``max_per_type`` source items per type."""
    rng = np.random.default_rng(seed)
    degrade_config = degrade_config or DegradeConfig()
    arr = data.arrays()
    bg = CROP_CLASSES.index(BACKGROUND)
    obj = np.flatnonzero((arr["category"] != bg) & ~arr["reference"])
    background = np.flatnonzero(arr["category"] == bg)
    draw = _Draw(data, arr, obj, rng, max_per_type)
    qs = _scene_questions(draw)
    qs |= _crop_questions(draw, background, degrade_config)
    qs["visual_fidelity"] = _visual_fidelity(draw)
    qs["textual_fidelity"] = _textual_fidelity(draw)
    qs["cross_view_consistency"] = _cross_view_consistency(draw)
    return qs


def _scene_questions(draw: _Draw) -> dict[str, QuestionSet]:
    """Weather and time of day. Scene questions are asked of one camera view at a time, as the
    report asks them: each view of a sampled frame is a question of its own, grouped by view."""
    data, rng = draw.data, draw.rng
    frames = np.stack(data.scene_frames) if data.scene_frames else np.zeros((0, 1, 1, 1, 3), np.uint8)
    views = frames.shape[1]
    fidx = draw.sub(np.arange(len(frames)))
    single = frames[fidx].reshape(len(fidx) * views, 1, *frames.shape[2:])
    view_names = [f"view {k}" for k in range(views)] * len(fidx)
    qs: dict[str, QuestionSet] = {}
    for name, labels, vocab in (("weather", data.weather, WEATHERS), ("time_of_day", data.time_of_day, TIMES_OF_DAY)):
        true = [vocab[labels[i]] for i in fidx for _ in range(views)]
        asked = true + [_pick_other(rng, vocab, t) for t in true]
        qs[name] = QuestionSet(
            a=np.concatenate([single, single]),
            asked=asked,
            label=np.r_[np.ones(len(single), bool), np.zeros(len(single), bool)],
            group=view_names * 2,
        )
    return qs


def _crop_questions(draw: _Draw, background: np.ndarray, degrade_config: DegradeConfig) -> dict[str, QuestionSet]:
    """Existence (objects' categories, and background crops asked about any), clarity (a crop
    against its degraded copy) and colour, each of one crop."""
    data, arr, obj, rng, cat = draw.data, draw.arr, draw.obj, draw.rng, draw.cat
    qs: dict[str, QuestionSet] = {}
    o, g = draw.sub(obj), draw.sub(background)
    qs["existence"] = QuestionSet(
        a=[data.crops[i] for i in o] * 2 + [data.crops[i] for i in g],
        asked=[cat(i) for i in o]
        + [_pick_other(rng, CATEGORIES, cat(i)) for i in o]
        + [CATEGORIES[int(rng.integers(len(CATEGORIES)))] for _ in g],
        label=np.r_[np.ones(len(o), bool), np.zeros(len(o) + len(g), bool)],
        group=[cat(i) for i in o] * 2 + [BACKGROUND] * len(g),
    )
    qs["clarity"] = QuestionSet(
        a=[data.crops[i] for i in o] + [degrade(data.crops[i], rng, degrade_config) for i in o],
        label=np.r_[np.ones(len(o), bool), np.zeros(len(o), bool)],
        group=[cat(i) for i in o] * 2,
    )
    colored = draw.sub(obj[arr["color"][obj] >= 0])
    qs["color"] = QuestionSet(
        a=[data.crops[i] for i in colored] * 2,
        asked=[COLOR_CLASSES[arr["color"][i]] for i in colored]
        + [_pick_other(rng, COLOR_CLASSES, COLOR_CLASSES[arr["color"][i]]) for i in colored],
        label=np.r_[np.ones(len(colored), bool), np.zeros(len(colored), bool)],
        group=[cat(i) for i in colored] * 2,
    )
    return qs


def _visual_fidelity(draw: _Draw) -> QuestionSet:
    """An object's crop beside its track's reference crop (yes) and another track's (no)."""
    data, arr, obj, rng, cat = draw.data, draw.arr, draw.obj, draw.rng, draw.cat
    ref_of = {int(arr["track"][i]): i for i in range(len(data.crops)) if arr["reference"][i]}
    refs = np.array(sorted(ref_of.values()), dtype=np.int64)
    with_ref = draw.sub(np.array([i for i in obj if int(arr["track"][i]) in ref_of], dtype=np.int64))
    pa, pb, lab, grp = [], [], [], []
    for i in with_ref:
        others = refs[arr["track"][refs] != arr["track"][i]]
        if len(others) == 0:
            continue
        pa += [data.crops[i], data.crops[i]]
        pb += [data.crops[ref_of[int(arr["track"][i])]], data.crops[int(rng.choice(others))]]
        lab += [True, False]
        grp += [cat(i)] * 2
    return QuestionSet(a=pa, b=pb, label=np.array(lab, bool), group=grp)


def _textual_fidelity(draw: _Draw) -> QuestionSet:
    """An object's crop asked about its own description (yes) and a different one (no)."""
    data, obj, rng, cat = draw.data, draw.obj, draw.rng, draw.cat
    parsed = {i: parse_description(data.description[i]) for i in obj}
    readable = draw.sub(np.array([i for i in obj if not parsed[i].empty], dtype=np.int64))
    ta, asked, lab, grp = [], [], [], []
    for i in readable:
        wrong = [j for j in readable if parsed[j] != parsed[i]]
        if not wrong:
            continue
        ta += [data.crops[i]] * 2
        asked += [data.description[i], data.description[int(wrong[int(rng.integers(len(wrong)))])]]
        lab += [True, False]
        grp += [cat(i)] * 2
    return QuestionSet(a=ta, asked=asked, label=np.array(lab, bool), group=grp)


def _cross_view_consistency(draw: _Draw) -> QuestionSet:
    """Crops of one frame in two views: the same track (yes), another track (no)."""
    data, arr, rng, cat = draw.data, draw.arr, draw.rng, draw.cat
    by_frame: dict[int, list[int]] = defaultdict(list)
    for i in draw.obj:
        by_frame[int(arr["frame"][i])].append(int(i))
    ca, cb, lab, grp = [], [], [], []
    for members in by_frame.values():
        for i in members:
            same = [j for j in members if arr["track"][j] == arr["track"][i] and arr["view"][j] > arr["view"][i]]
            diff = [j for j in members if arr["track"][j] != arr["track"][i] and arr["view"][j] != arr["view"][i]]
            if not same:
                continue
            j = min(same, key=lambda k: arr["view"][k])
            ca.append(data.crops[i])
            cb.append(data.crops[j])
            lab.append(True)
            grp.append(cat(i))
            if diff:
                ca.append(data.crops[i])
                cb.append(data.crops[int(diff[int(rng.integers(len(diff)))])])
                lab.append(False)
                grp.append(cat(i))
    return QuestionSet(a=ca, b=cb, label=np.array(lab, bool), group=grp)


def answer(backend: JudgeBackend, qtype: str, q: QuestionSet) -> np.ndarray:
    """The backend's yes/no answers (N,) to one question set."""
    if len(q.label) == 0:
        return np.zeros(0, dtype=bool)
    if qtype == "weather":
        return backend.is_weather(q.a, q.asked)
    if qtype == "time_of_day":
        return backend.is_time_of_day(q.a, q.asked)
    if qtype == "existence":
        return backend.is_category(q.a, q.asked)
    if qtype == "clarity":
        return backend.is_clear(q.a)
    if qtype == "visual_fidelity":
        return backend.same_object(q.a, q.b)
    if qtype == "textual_fidelity":
        return backend.matches_description(q.a, q.asked)
    if qtype == "cross_view_consistency":
        return backend.consistent(q.a, q.b)
    raise ValueError(f"unknown question type {qtype!r}; choose from {QUESTION_TYPES}")


def balanced_accuracy(pred: np.ndarray, label: np.ndarray) -> dict[str, float]:
    """Yes-rate on positives (tpr), no-rate on negatives (tnr), their mean, and counts."""
    pos, neg = label, ~label
    tpr = float(pred[pos].mean()) if pos.any() else float("nan")
    tnr = float((~pred[neg]).mean()) if neg.any() else float("nan")
    both = [v for v in (tpr, tnr) if v == v]
    return {
        "balanced_accuracy": float(np.mean(both)) if both else float("nan"),
        "tpr": tpr,
        "tnr": tnr,
        "n_pos": int(pos.sum()),
        "n_neg": int(neg.sum()),
    }


def judge_accuracy(
    backend: JudgeBackend, questions: dict[str, QuestionSet], types: Sequence[str] = QUESTION_TYPES
) -> dict[str, dict]:
    """Accuracy per question type (of ``types``), overall and per group (``per_category``): the
    category of the asked-about object, or the camera view of a scene question."""
    report = {}
    for qtype in types:
        q = questions[qtype]
        pred = np.asarray(answer(backend, qtype, q), dtype=bool)
        entry = balanced_accuracy(pred, q.label)
        groups = np.array(q.group)
        entry["per_category"] = {
            g: balanced_accuracy(pred[groups == g], q.label[groups == g]) for g in sorted(set(q.group))
        }
        report[qtype] = entry
    return report
