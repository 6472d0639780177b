"""Train the default judge backend on ground-truth procedural crops, calibrate, and save it.

``python -m world_model.eval.train_judge --data DIR [DIR ...] --out DIR``. Clips are split by clip
into train / validation (every ``val_every``-th clip); the networks train on the first, the yes
thresholds are calibrated on the second (balanced accuracy), and the validation accuracy per
question is stored in ``judge.json`` (``info.validation``). Deterministic for a fixed machine and
thread count: seeded sampling, deterministic torch algorithms.

The scene network answers weather and time of day for one camera view at a time (the report asks
every view on its own), so it trains on single views, each labelled with its frame's weather and
time. ``--keep-crop-net JUDGE`` trains only the scene network and keeps that judge's object
network with its thresholds: the object questions (existence, clarity, fidelity, consistency)
answer exactly as before.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F

from world_model.data import list_clips
from world_model.eval.crops import crop_statistics, normalize_crops
from world_model.eval.judge import CnnJudge, JudgeThresholds, load_judge
from world_model.eval.judge_data import VIEW_JITTER, CollectConfig, DegradeConfig, JudgeData, collect, degrade
from world_model.eval.nets import BACKGROUND, COLOR_CLASSES, CROP_CLASSES, CropNet, JudgeNetConfig, SceneNet
from world_model.eval.questions import build_questions, judge_accuracy
from world_model.scene import CATEGORIES, TIMES_OF_DAY, WEATHERS


@dataclass(frozen=True)
class TrainJudgeConfig:
    """Everything the judge's training run depends on."""

    net: JudgeNetConfig = field(default_factory=JudgeNetConfig)
    collect: CollectConfig = field(default_factory=CollectConfig)
    degrade: DegradeConfig = field(default_factory=DegradeConfig)
    view_jitter: DegradeConfig = VIEW_JITTER  # weather- and time-preserving jitter of training views
    view_jitter_share: float = 0.5  # of the scene network's training views
    val_every: int = 7  # every 7th clip (sorted by dataset, then name) is held out for calibration
    seed: int = 0
    threads: int = 2
    crop_steps: int = 1200
    tracks_per_batch: int = 48  # two crops of each -> pairs for the same-object head
    background_per_batch: int = 32
    scene_steps: int = 3000
    scene_batch: int = 12
    lr: float = 2e-3
    weight_decay: float = 1e-4
    color_weight: float = 0.5
    pair_weight: float = 1.0
    clarity_weight: float = 0.5


def _split(roots: list[Path], val_every: int) -> tuple[list[tuple[Path, str]], list[tuple[Path, str]]]:
    items = [(r, n) for r in roots for n in sorted(list_clips(r))]
    val = [x for i, x in enumerate(items) if i % val_every == val_every - 1]
    train = [x for i, x in enumerate(items) if i % val_every != val_every - 1]
    return train, val


def _collect_many(items: list[tuple[Path, str]], config: CollectConfig) -> JudgeData:
    merged = JudgeData()
    for root in dict.fromkeys(r for r, _ in items):
        part = collect(root, config, [n for r, n in items if r == root])
        offset_clip, offset_track = len(merged.clip_names), max(merged.track, default=-1) + 1
        offset_frame = max(merged.frame, default=-1) + 1
        merged.clip_names += part.clip_names
        for i in range(len(part.crops)):
            labels = part.labels(i)
            t, f = labels.track, labels.frame
            track, frame = t + offset_track if t >= 0 else -1, f + offset_frame if f >= 0 else -1
            merged.add_crop(part.crops[i], replace(labels, track=track, frame=frame, clip=labels.clip + offset_clip))
        merged.scene_frames += part.scene_frames
        merged.weather += part.weather
        merged.time_of_day += part.time_of_day
        merged.scene_clip += [c + offset_clip for c in part.scene_clip]
    return merged


def _train_crop_net(data: JudgeData, cfg: TrainJudgeConfig, log: Callable[[str], None]) -> CropNet:
    rng = np.random.default_rng([cfg.seed, 1])
    size = cfg.net.crop_size
    arr = data.arrays()
    degraded = [degrade(c, rng, cfg.degrade) for c in data.crops]
    clean = torch.from_numpy(normalize_crops(data.crops, size))
    dirty = torch.from_numpy(normalize_crops(degraded, size))
    stats_clean = torch.from_numpy(crop_statistics(data.crops))
    stats_dirty = torch.from_numpy(crop_statistics(degraded))
    category, color = torch.from_numpy(arr["category"]), torch.from_numpy(arr["color"])
    bg = CROP_CLASSES.index(BACKGROUND)
    background = np.flatnonzero(arr["category"] == bg)
    tracks: dict[int, list[int]] = {}
    for i in np.flatnonzero(arr["track"] >= 0):
        tracks.setdefault(int(arr["track"][i]), []).append(int(i))
    by_cat: dict[int, list[int]] = {}
    for t, members in tracks.items():
        if len(members) >= 2:
            by_cat.setdefault(int(arr["category"][members[0]]), []).append(t)
    cats = sorted(by_cat)
    net = CropNet(cfg.net)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.lr, total_steps=cfg.crop_steps)
    for step in range(cfg.crop_steps):
        # Category-balanced tracks (rare categories are seen as often as cars), two crops each.
        picked = [by_cat[c][int(rng.integers(len(by_cat[c])))] for c in rng.choice(cats, cfg.tracks_per_batch)]
        idx = [i for t in picked for i in rng.choice(tracks[t], 2, replace=False)]
        idx += rng.choice(background, cfg.background_per_batch).tolist()
        idx_t = torch.tensor(idx)
        flip = torch.from_numpy(rng.random(len(idx)) < 0.5)
        x = clean[idx_t]
        x = torch.where(flip[:, None, None, None], x.flip(3), x)
        half = torch.from_numpy(rng.random(len(idx)) < 0.5)
        x_clarity = torch.where(half[:, None, None, None], dirty[idx_t], x)
        s_clarity = torch.where(half[:, None], stats_dirty[idx_t], stats_clean[idx_t])
        out = net(torch.cat([x, x_clarity]), torch.cat([stats_clean[idx_t], s_clarity]))
        k = len(idx)
        loss = F.cross_entropy(out["category"][:k], category[idx_t])
        col = color[idx_t]
        if (col >= 0).any():
            loss = loss + cfg.color_weight * F.cross_entropy(out["color"][:k][col >= 0], col[col >= 0])
        loss = loss + cfg.clarity_weight * F.binary_cross_entropy_with_logits(out["clarity"][k:], (~half).float())
        e = out["embedding"][: 2 * cfg.tracks_per_batch]
        tr = torch.tensor([t for t in picked for _ in range(2)])
        same = (tr[:, None] == tr[None, :]).float()
        logits = net.pair_scale * (e @ e.T) + net.pair_bias
        off = ~torch.eye(len(e), dtype=torch.bool)
        # Positives are rare among all pairs: weight them up to balance the loss.
        w = torch.where(same.bool(), (off.sum() - same[off].sum()) / same[off].sum().clamp(min=1), 1.0)
        loss = loss + cfg.pair_weight * F.binary_cross_entropy_with_logits(logits[off], same[off], weight=w[off])
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 200 == 0 or step == cfg.crop_steps - 1:
            log(f"crop step {step}: loss {loss.item():.3f}")
    return net.eval()


def _train_scene_net(data: JudgeData, cfg: TrainJudgeConfig, log: Callable[[str], None]) -> SceneNet:
    """Weather and time of day of single camera views: every view of ``scene_batch`` sampled frames
    is one example with its frame's labels. A share of the views is jittered (``view_jitter``) so
    that the answer rests on what a viewer would call weather and light, not on single pixels: a
    network trained on clean views alone called a fog scene snow once blurred by 0.7 px."""
    rng = np.random.default_rng([cfg.seed, 2])
    frames = np.stack(data.scene_frames)
    views = frames.shape[1]
    weather, tod = torch.tensor(data.weather), torch.tensor(data.time_of_day)
    net = SceneNet(cfg.net)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.lr, total_steps=cfg.scene_steps)
    for step in range(cfg.scene_steps):
        idx = rng.choice(len(frames), cfg.scene_batch, replace=False)
        batch = frames[idx].copy()
        for i, k in np.argwhere(rng.random(batch.shape[:2]) < cfg.view_jitter_share):
            batch[i, k] = degrade(batch[i, k], rng, cfg.view_jitter)
        x = torch.from_numpy(batch).permute(0, 1, 4, 2, 3).float() / 255.0
        x = x.flatten(0, 1).unsqueeze(1)  # (B * V, 1, 3, H, W): each view alone
        if rng.random() < 0.5:  # mirror the views: weather and time do not care
            x = x.flip(4)
        out = net(x)
        w, t = weather[idx].repeat_interleave(views), tod[idx].repeat_interleave(views)
        loss = F.cross_entropy(out["weather"], w) + F.cross_entropy(out["time_of_day"], t)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 100 == 0 or step == cfg.scene_steps - 1:
            log(f"scene step {step}: loss {loss.item():.3f}")
    return net.eval()


def _best_threshold(prob: np.ndarray, label: np.ndarray) -> float:
    """The threshold maximizing balanced accuracy of ``prob >= t`` (0.5 without both classes)."""
    if len(prob) == 0 or label.all() or not label.any():
        return 0.5
    best, best_t = -1.0, 0.5
    for t in np.unique(np.r_[prob, 0.5]):
        pred = prob >= t
        acc = 0.5 * (pred[label].mean() + (~pred[~label]).mean())
        if acc > best + 1e-12:
            best, best_t = acc, float(t)
    return best_t


def calibrate(judge: CnnJudge, data: JudgeData, seed: int = 0) -> JudgeThresholds:
    """Thresholds maximizing balanced accuracy on the question sets of ``data``."""
    qs = build_questions(data, seed=seed)

    def pick(probs: np.ndarray, asked: list[str], vocab: tuple[str, ...]) -> np.ndarray:
        return probs[np.arange(len(probs)), [vocab.index(a) for a in asked]]

    t = {}
    scene = judge.scene_outputs(qs["weather"].a) if len(qs["weather"].label) else None
    if scene is not None:
        t["weather"] = _best_threshold(pick(scene["weather"], qs["weather"].asked, WEATHERS), qs["weather"].label)
        tq = qs["time_of_day"]
        t["time_of_day"] = _best_threshold(pick(scene["time_of_day"], tq.asked, TIMES_OF_DAY), tq.label)
    q = qs["existence"]
    t["category"] = _best_threshold(pick(judge.crop_outputs(q.a)["category"], q.asked, CATEGORIES), q.label)
    q = qs["color"]
    t["color"] = _best_threshold(pick(judge.crop_outputs(q.a)["color"], q.asked, COLOR_CLASSES), q.label)
    q = qs["clarity"]
    t["clarity"] = _best_threshold(judge.crop_outputs(q.a)["clarity"], q.label)
    for name, key in (("visual_fidelity", "visual_fidelity"), ("cross_view_consistency", "consistency")):
        q = qs[name]
        if len(q.label):
            ea, eb = judge.crop_outputs(q.a)["embedding"], judge.crop_outputs(q.b)["embedding"]
            t[key] = _best_threshold(judge.pair_probs(ea, eb), q.label)
    return JudgeThresholds(**t)


def train_judge(
    data_dirs: Sequence[str | Path],
    out_dir: str | Path,
    config: TrainJudgeConfig = TrainJudgeConfig(),
    log: Callable[[str], None] = print,
    keep_crop_net: str | Path | None = None,
) -> CnnJudge:
    """Train, calibrate and save the judge; returns it. ``judge.json`` records the validation accuracy.
    ``keep_crop_net``: a saved judge whose object network and object thresholds are kept (only the
    scene network trains; its crop sampling settings are that judge's).

    Torch's thread count and deterministic-algorithms flag are set for the run and restored after.
    """
    threads, deterministic = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(config.threads)
    torch.use_deterministic_algorithms(True)
    try:
        kept = None if keep_crop_net is None else load_judge(keep_crop_net)
        return _train_judge(data_dirs, out_dir, config, log, kept)
    finally:
        torch.set_num_threads(threads)
        torch.use_deterministic_algorithms(deterministic)


def _train_judge(
    data_dirs: Sequence[str | Path],
    out_dir: str | Path,
    config: TrainJudgeConfig,
    log: Callable[[str], None],
    kept: CnnJudge | None,
) -> CnnJudge:
    start = time.time()
    torch.manual_seed(config.seed)
    roots = [Path(d) for d in data_dirs]
    train_items, val_items = _split(roots, config.val_every)
    if not train_items or not val_items:
        raise ValueError(f"need clips for both training and validation in {data_dirs} (val_every={config.val_every})")
    log(f"collecting crops from {len(train_items)} training and {len(val_items)} validation clips")
    train_data, val_data = _collect_many(train_items, config.collect), _collect_many(val_items, config.collect)
    log(f"train: {len(train_data.crops)} crops, {len(train_data.scene_frames)} frames")
    crop_net = _train_crop_net(train_data, config, log) if kept is None else kept.crop_net
    scene_net = _train_scene_net(train_data, config, log)
    judge = CnnJudge(crop_net, scene_net, crop_config=config.collect.crop if kept is None else kept.crop_config)
    calibrated = calibrate(judge, val_data, seed=config.seed)
    if kept is None:
        judge.thresholds = calibrated
    else:  # the kept object network answers with its own thresholds
        judge.thresholds = replace(kept.thresholds, weather=calibrated.weather, time_of_day=calibrated.time_of_day)
    validation = judge_accuracy(judge, build_questions(val_data, seed=config.seed + 1))
    judge.info = {
        **({} if kept is None else {"crop_net_from": kept.info}),
        "train_config": _config_dict(config),
        "train_clips": len(train_items),
        "validation_clips": len(val_items),
        "data_dirs": [r.name for r in roots],  # folder names only: shipped metadata names no machine path
        "validation": validation,
        "train_seconds": round(time.time() - start, 1),
    }
    judge.save(out_dir)
    for q, v in validation.items():
        log(f"validation {q}: balanced accuracy {v['balanced_accuracy']:.3f} (n={v['n_pos']}+{v['n_neg']})")
    return judge


def _config_dict(config: TrainJudgeConfig) -> dict:
    def clean(x: Any) -> Any:
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (tuple, list)):
            return [clean(v) for v in x]
        return x

    return clean(asdict(config))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="train the default (CNN) judge backend")
    p.add_argument("--data", nargs="+", required=True, help="recorded dataset directories")
    p.add_argument("--out", required=True, help="output directory (judge.safetensors + judge.json)")
    p.add_argument("--crop-steps", type=int, default=TrainJudgeConfig.crop_steps)
    p.add_argument("--scene-steps", type=int, default=TrainJudgeConfig.scene_steps)
    p.add_argument("--max-clips", type=int, default=None, help="use only the first N clips of each directory")
    p.add_argument(
        "--keep-crop-net",
        metavar="JUDGE",
        help="a saved judge (e.g. world_model/assets/judge) whose object network and thresholds are kept; "
        "only the scene network (weather, time of day) trains",
    )
    args = p.parse_args(argv)
    cfg = TrainJudgeConfig(
        crop_steps=args.crop_steps,
        scene_steps=args.scene_steps,
        collect=CollectConfig(max_clips=args.max_clips),
    )
    train_judge(args.data, args.out, cfg, keep_crop_net=args.keep_crop_net)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
