"""Train the segmenter on recorded ground-truth camera views, measure it on held-out clips, save it.

``python -m world_model.eval.train_segmenter --data DIR [DIR ...] --heldout DIR [DIR ...]
[--evalset DIR] --work DIR --out DIR`` (``make segmenter`` records the data and runs it). The held-out
clips must be recorded with other seeds than the training clips; the evaluation set (when given)
gives the "oracle" figure: the segmenter on the recordings the report scores. Label maps are cached
and training checkpoints written atomically under ``--work``; a killed or time-limited run
(``--max-minutes``) continues from its last checkpoint when started again with the same settings.
Sampling draws from a generator seeded by (seed, step), so a resumed run sees the batches an
uninterrupted one would have.

``segmenter.json`` records the classes, the data, the held-out and oracle per-class IoU, and the IoU
on a small slice of one held-out clip (``check_slice``) that a test re-records and re-measures.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.nn import functional as F

from world_model.data import read_clip, write_json_atomic
from world_model.eval.metrics import ConfusionSums, confusion_sums
from world_model.eval.segmenter import NUM_SCENE_CLASSES, SCENE_CLASSES, Segmenter, SegmenterConfig, SegNet
from world_model.eval.segmenter_data import ClipRef, ViewSet, clip_refs, collect_views
from world_model.train.checkpoint import load_latest, save_checkpoint

RECIPE = "make segmenter"  # the Makefile target that records the data and runs this command
RARE = (SCENE_CLASSES.index("vulnerable"), SCENE_CLASSES.index("other_object"))


@dataclass(frozen=True)
class AugmentConfig:
    """Photometric and geometric changes of training views: generated frames are blurrier, noisier
    and shifted in colour compared with the recordings the segmenter learns from."""

    flip: float = 0.5  # probability of a horizontal mirror (image and labels)
    gain: tuple[float, float] = (0.6, 1.4)  # brightness multiplier
    channel_gain: float = 0.15  # per-channel multiplier in 1 +- this
    # added, as a fraction of the view's mean level: a night view's road differs from the ground by
    # a few levels, which a fixed shift of tens of levels would clip away
    bias: tuple[float, float] = (-0.2, 0.2)
    blur: float = 0.35  # probability of a Gaussian blur
    blur_sigma: tuple[float, float] = (0.5, 1.5)  # pixels
    noise: float = 0.25  # probability of additive Gaussian noise
    noise_std: tuple[float, float] = (2.0, 12.0)  # 0-255 scale


@dataclass(frozen=True)
class TrainSegmenterConfig:
    """Everything the segmenter's training run depends on."""

    net: SegmenterConfig = field(default_factory=SegmenterConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    seed: int = 0
    threads: int = 2
    steps: int = 6000
    batch_size: int = 24  # camera views per step
    lr: float = 3e-3
    weight_decay: float = 1e-4
    dice_weight: float = 0.5  # soft Dice beside cross-entropy: IoU-like, not dominated by the sky
    class_weight_power: float = 0.5  # cross-entropy weight of a class: (its pixel frequency) ** -power
    max_class_weight: float = 10.0  # relative to the mean weight
    rare_view_weight: float = 4.0  # views showing a pedestrian, cyclist, cone or barrier are drawn this much more
    train_stride: int = 1  # every n-th frame of the training clips
    heldout_stride: int = 4  # every n-th frame of the held-out clips
    evalset_stride: int = 10  # every n-th frame of the evaluation set's clips
    check_frames: int = 4  # frames of one held-out clip in the check slice (every heldout_stride-th)
    ckpt_every: int = 250
    log_every: int = 50


def augment(
    images: np.ndarray, labels: np.ndarray, rng: np.random.Generator, config: AugmentConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 views (B, H, W, 3) and labels (B, H, W) -> float images (B, 3, H, W) in [0, 1] and int64
    labels (B, H, W), each view changed at random by ``config``."""
    out = np.empty(images.shape, dtype=np.float32)
    labs = np.array(labels, dtype=np.int64)
    for i, img in enumerate(images):
        x = img.astype(np.float32)
        if rng.random() < config.flip:
            x, labs[i] = x[:, ::-1], labs[i][:, ::-1]
        gain = rng.uniform(*config.gain) * (1.0 + rng.uniform(-config.channel_gain, config.channel_gain, 3))
        x = x * gain.astype(np.float32) + np.float32(rng.uniform(*config.bias) * x.mean())
        if rng.random() < config.blur:
            x = cv2.GaussianBlur(np.ascontiguousarray(x), (0, 0), rng.uniform(*config.blur_sigma))
        if rng.random() < config.noise:
            x = x + rng.normal(0.0, rng.uniform(*config.noise_std), x.shape).astype(np.float32)
        out[i] = np.clip(x, 0.0, 255.0)
    return torch.from_numpy(out).permute(0, 3, 1, 2) / 255.0, torch.from_numpy(labs)


def class_weights(labels: np.ndarray, power: float, max_weight: float) -> np.ndarray:
    """(C,) cross-entropy weights, (pixel frequency) ** -power, mean 1, capped at ``max_weight``;
    classes never labelled get the cap."""
    freq = np.bincount(labels.ravel(), minlength=NUM_SCENE_CLASSES).astype(np.float64) / labels.size
    w = np.where(freq > 0, np.maximum(freq, 1e-12) ** -power, np.inf)
    w = w / w[np.isfinite(w)].mean()
    return np.minimum(w, max_weight)


def soft_dice_loss(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """1 - mean soft Dice over the classes labelled in the batch: logits (B, C, H, W), labels (B, H, W)."""
    probs = logits.softmax(1)
    onehot = F.one_hot(labels, logits.shape[1]).permute(0, 3, 1, 2).to(probs.dtype)
    inter = (probs * onehot).sum(dim=(0, 2, 3))
    total = probs.sum(dim=(0, 2, 3)) + onehot.sum(dim=(0, 2, 3))
    present = onehot.sum(dim=(0, 2, 3)) > 0
    dice = (2.0 * inter + 1.0) / (total + 1.0)
    return 1.0 - dice[present].mean()


def evaluate(segmenter: Segmenter, views: ViewSet, select: np.ndarray | None = None) -> ConfusionSums:
    """Pixel sums of the segmenter on ``views`` (all, or the indices ``select``)."""
    idx = np.arange(len(views.images)) if select is None else select
    sums = ConfusionSums.zeros(NUM_SCENE_CLASSES)
    for i in range(0, len(idx), 512):
        part = idx[i : i + 512]
        sums = sums + confusion_sums(segmenter.predict(views.images[part]), views.labels[part], NUM_SCENE_CLASSES)
    return sums


def _by_class(values: list[float | None]) -> dict[str, float | None]:
    return {c: (None if v is None else round(v, 4)) for c, v in zip(SCENE_CLASSES, values, strict=True)}


def _recording(root: Path) -> dict:
    path = root / "recording.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing: held-out clips must be recorded by `m4world record`")
    return json.loads(path.read_text())


def _check_slice(refs: Sequence[ClipRef], views: ViewSet, segmenter: Segmenter, config: TrainSegmenterConfig) -> dict:
    """The IoU on the first ``check_frames`` sampled frames of the held-out clip whose sampled
    views show the most vehicle pixels, with what it takes to record that clip again."""
    vehicle = SCENE_CLASSES.index("vehicle")
    counts = [int((views.labels[views.clip == i] == vehicle).sum()) for i in range(len(refs))]
    ci = int(np.argmax(counts))
    ref = refs[ci]
    meta = read_clip(ref.root, ref.name).meta
    per_frame = len(meta["camera_names"])
    select = np.flatnonzero(views.clip == ci)[: config.check_frames * per_frame]
    sums = evaluate(segmenter, views, select)
    return {
        "clip": ref.name,
        "scenario": meta["base_scenario"],
        "seed": meta["seed"],
        "recording": _recording(ref.root),
        "frames": list(range(0, config.check_frames * config.heldout_stride, config.heldout_stride)),
        "iou": _by_class(sums.iou()),
    }


def _config_dict(config: TrainSegmenterConfig) -> dict:
    return json.loads(json.dumps(asdict(config)))


def _command_path(path: str | Path) -> str:
    """A path as written into shipped metadata: relative paths as given, absolute ones by name."""
    p = Path(path)
    return p.name if p.is_absolute() else p.as_posix()


def train_segmenter(
    data_dirs: Sequence[str | Path],
    heldout_dirs: Sequence[str | Path],
    out_dir: str | Path,
    work_dir: str | Path,
    evalset_dir: str | Path | None = None,
    config: TrainSegmenterConfig = TrainSegmenterConfig(),
    max_minutes: float | None = None,
    log: Callable[[str], None] = print,
) -> Segmenter | None:
    """Train (resuming from ``work_dir``), measure and save the segmenter; returns it, or None when
    ``max_minutes`` ran out first (the checkpoint in ``work_dir`` continues the run).

    Torch's thread count and deterministic-algorithms flag are set for the run and restored after."""
    threads, deterministic = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(config.threads)
    torch.use_deterministic_algorithms(True)
    try:
        return _train(data_dirs, heldout_dirs, out_dir, Path(work_dir), evalset_dir, config, max_minutes, log)
    finally:
        torch.set_num_threads(threads)
        torch.use_deterministic_algorithms(deterministic)


def _sampling_weights(labels: np.ndarray, config: TrainSegmenterConfig) -> tuple[np.ndarray, np.ndarray]:
    """The loss's class weights, and each training view's chance of being drawn (views holding a
    rare class more often)."""
    weights = class_weights(labels, config.class_weight_power, config.max_class_weight)
    rare = np.isin(labels, RARE).any(axis=(1, 2))
    draw = np.where(rare, config.rare_view_weight, 1.0)
    draw /= draw.sum()
    return weights, draw


def _report_progress(path: Path, done: int, steps: int, loss: float, rate: float, log: Callable[[str], None]) -> None:
    """Log the step, loss, speed and time left, and write them to ``path`` (JSON)."""
    eta = (steps - done) / rate
    log(f"step {done}/{steps}: loss {loss:.4f}, {rate:.2f} steps/s, {eta / 60:.1f} min left")
    progress = {"step": done, "steps": steps, "loss": loss, "steps_per_s": rate, "eta_s": eta}
    write_json_atomic(path, progress)


def _resume(checkpoints: Path, settings: dict, state: tuple, log: Callable[[str], None]) -> int:
    """The step to start at: 0, or the latest checkpoint's, its net, optimizer and scheduler
    (``state``) loaded; a checkpoint of other ``settings`` is refused."""
    if (ckpt := load_latest(checkpoints)) is None:
        return 0
    if ckpt.meta.get("config") != settings:
        raise ValueError(f"{checkpoints} holds a run with other settings; use another --work folder or delete it")
    net, opt, sched = state
    net.load_state_dict(ckpt.tensors["model"])
    opt.load_state_dict(ckpt.train_state["optimizer"])
    sched.load_state_dict(ckpt.train_state["scheduler"])
    log(f"resuming at step {ckpt.step}")
    return ckpt.step


def _command(
    data_dirs: Sequence[str | Path],
    heldout_dirs: Sequence[str | Path],
    evalset_dir: str | Path | None,
    work: Path,
    out_dir: str | Path,
) -> str:
    """The command line that trains this segmenter again, for its info."""
    return " ".join(
        [
            "python -m world_model.eval.train_segmenter",
            "--data",
            *map(_command_path, data_dirs),
            "--heldout",
            *map(_command_path, heldout_dirs),
        ]
        + (["--evalset", _command_path(evalset_dir)] if evalset_dir is not None else [])
        + ["--work", _command_path(work), "--out", _command_path(out_dir)]
    )  # fmt: skip


def _oracle_evalset(
    segmenter: Segmenter,
    evalset_dir: str | Path,
    work: Path,
    config: TrainSegmenterConfig,
    log: Callable[[str], None],
) -> dict:
    """The segmenter's IoU per class on the evaluation set's clips (the oracle row of the report)."""
    eval_refs = clip_refs([evalset_dir])
    ev = collect_views(eval_refs, work / "labels", config.evalset_stride)
    ev_sums = evaluate(segmenter, ev)
    result = {"clips": len(eval_refs), "views": len(ev.images), "iou": _by_class(ev_sums.iou())}
    for c, v in result["iou"].items():
        log(f"evaluation set (oracle) IoU {c}: {v}")
    return result


def _train(
    data_dirs: Sequence[str | Path],
    heldout_dirs: Sequence[str | Path],
    out_dir: str | Path,
    work: Path,
    evalset_dir: str | Path | None,
    config: TrainSegmenterConfig,
    max_minutes: float | None,
    log: Callable[[str], None],
) -> Segmenter | None:
    start = time.time()
    train_refs, held_refs = clip_refs(data_dirs), clip_refs(heldout_dirs)
    shared = {r.name for r in train_refs} & {r.name for r in held_refs}
    if shared:
        raise ValueError(f"held-out clips must not be training clips; both hold {sorted(shared)[:3]} ...")
    log(f"label maps of {len(train_refs)} training clips (cached in {work / 'labels'})")
    train = collect_views(train_refs, work / "labels", config.train_stride)
    log(f"train: {len(train.images)} views")
    weights, draw = _sampling_weights(train.labels, config)

    torch.manual_seed(config.seed)
    net = SegNet(config.net)
    opt = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, config.lr, total_steps=config.steps)
    settings = _config_dict(config)
    first = _resume(work / "checkpoints", settings, (net, opt, sched), log)
    w = torch.from_numpy(weights).float()
    net.train()
    step_start, seen_start = time.time(), first
    for step in range(first, config.steps):
        rng = np.random.default_rng([config.seed, step])
        idx = rng.choice(len(train.images), config.batch_size, p=draw)
        x, y = augment(train.images[idx], train.labels[idx], rng, config.augment)
        logits = net(x)
        loss = F.cross_entropy(logits, y, weight=w) + config.dice_weight * soft_dice_loss(logits, y)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        done = step + 1
        if done % config.log_every == 0 or done == config.steps:
            rate = (done - seen_start) / max(time.time() - step_start, 1e-9)
            _report_progress(work / "progress.json", done, config.steps, loss.item(), rate, log)
        out_of_time = max_minutes is not None and time.time() - start > 60.0 * max_minutes
        if done % config.ckpt_every == 0 or done == config.steps or out_of_time:
            state = {"optimizer": opt.state_dict(), "scheduler": sched.state_dict()}
            save_checkpoint(work / "checkpoints", done, {"model": net.state_dict()}, state, {"config": settings})
        if out_of_time and done < config.steps:
            log(f"stopped at step {done} after {max_minutes} min; run the same command again to continue")
            return None

    segmenter = Segmenter(net.eval())
    log(f"measuring on {len(held_refs)} held-out clips")
    held = collect_views(held_refs, work / "labels", config.heldout_stride)
    held_sums = evaluate(segmenter, held)
    info = {
        "recipe": RECIPE,
        "command": _command(data_dirs, heldout_dirs, evalset_dir, work, out_dir),
        "train": {"clips": len(train_refs), "views": len(train.images), "recording": _recording(train_refs[0].root)},
        "heldout": {
            "clips": len(held_refs),
            "views": len(held.images),
            "iou": _by_class(held_sums.iou()),
            "accuracy": _by_class(held_sums.accuracy()),
        },
        "class_weights": [round(float(v), 4) for v in weights],
        "train_config": settings,
    }
    for c, v in info["heldout"]["iou"].items():
        log(f"held-out IoU {c}: {v}")
    if evalset_dir is not None:
        info["oracle_evalset"] = _oracle_evalset(segmenter, evalset_dir, work, config, log)
    info["check_slice"] = _check_slice(held_refs, held, segmenter, config)
    info["train_seconds"] = round(time.time() - start, 1)
    segmenter.info = info
    segmenter.save(out_dir)
    log(f"saved {out_dir}")
    return segmenter


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="train the segmenter of the scene IoU metric")
    p.add_argument("--data", nargs="+", required=True, help="recorded training dataset directories")
    p.add_argument("--heldout", nargs="+", required=True, help="recorded datasets of other seeds, for the held-out IoU")
    p.add_argument("--evalset", default=None, help="the evaluation set (m4world evalset), for the oracle IoU")
    p.add_argument("--work", required=True, help="label cache, checkpoints and progress.json (resumable)")
    p.add_argument("--out", required=True, help="output directory (segmenter.safetensors + segmenter.json)")
    p.add_argument("--steps", type=int, default=TrainSegmenterConfig.steps)
    p.add_argument("--max-minutes", type=float, default=None, help="stop (checkpointed) after this many minutes")
    args = p.parse_args(argv)
    if args.steps < 1:
        p.error(f"--steps must be positive, got {args.steps}")
    cfg = TrainSegmenterConfig(steps=args.steps)
    done = train_segmenter(args.data, args.heldout, args.out, args.work, args.evalset, cfg, args.max_minutes)
    return 0 if done is not None else 3


if __name__ == "__main__":
    raise SystemExit(main())
