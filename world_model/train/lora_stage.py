"""``--stage lora --case NAME`` (§5): one LoRA adapter per long-tail case, base model frozen.

Layout::

    RUN_DIR/lora/NAME/   model_config.json, checkpoints/, adapter.safetensors + adapter.json

Data selection: the *rare* clips are the clips containing an object of category ``NAME`` (or the
explicit ``case_clips``), taken from ``case_data`` when given, else from ``data``; the *ordinary*
clips are the clips of ``data`` without that category. :class:`BalancedSampler` draws every
training example from the rare pool with probability ``rare_fraction`` (paper: 50%) and from the
ordinary pool otherwise; a rare window starts on a frame where the rare object is present, so
its object token is in the conditions.

A reference model as base (``--base RUN/reference/model``, §6) is adapted in the tasks it serves:
a rare window asks it to complete the rare objects (everything observed except their boxes, as
the reference stage's object completion with the rare category as the object), an ordinary window
gets a task drawn from the reference stage's mix (:func:`world_model.model.reference.task_mask`).
Windows keep the lengths of ``clip.train_frames``: the reference stage's single-frame batches
(``first_frame_only_prob``) are not repeated here.

Loss: the flow-matching loss of the base's pretraining, optionally weighted (``box_weight`` > 0)
by ``1 + box_weight`` on the latent cells the rare object's projected 3-D box covers, in every
view (LiDAR too) and frame where it is present (:func:`world_model.model.reference.object_region`,
no margin). The paper binds the rare object "within the specified 3D box" (§5); at a small
preset the box covers a few of a view's latent cells, so the plain mean spends almost all of the
rare clips' signal on the background the base already draws. The weighted mean is taken over the
whole batch, so rare windows weigh more than ``rare_fraction`` of the loss when the weight is on.

The base (default ``RUN_DIR/teacher/model``; ``base`` may point at any exported DiT, e.g. the
causal student, or at a checkpoint bundle such as the shipped default, whose student, or with
``BUNDLE/reference.safetensors`` its reference model, is adapted with the bundle's own VAE: no
training run needed) is loaded, fingerprinted
(:func:`world_model.lora.base_fingerprint`) and frozen; only the adapter trains. The adapter's
EMA weights are exported (the EMA warm-up makes them track a few-hundred-step run closely).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from world_model.bundle import sha256_file
from world_model.data import Clip
from world_model.lora import LoraConfig, add_adapter, base_fingerprint, save_adapter
from world_model.model.conditions import Conditions
from world_model.model.config import ModelConfig
from world_model.model.dit import MultiViewDiT
from world_model.model.flow import flow_matching_loss, sample_timesteps
from world_model.model.reference import TASKS, ReferenceConfig, category_region, reference_input, task_mask
from world_model.model.vae import SensorVAE
from world_model.train.data import LatentWindows, encoder_digest, load_clips
from world_model.train.exports import EXPORT, latent_windows, load_teacher, run_vae
from world_model.train.run import StageOptions, StageRun
from world_model.train.trainer import StepFn, Trainer

LORA_STEPS = 300  # "a few hundred iterations" (§5), whatever the preset


@dataclass(frozen=True)
class LoraStageConfig:
    rare_fraction: float = 0.5  # share of training examples drawn from the rare-case clips
    box_weight: float = 0.0  # extra loss weight inside the rare object's boxes (module docstring); 0 = plain
    lora: LoraConfig = field(default_factory=LoraConfig)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.box_weight) and self.box_weight >= 0.0):
            raise ValueError(f"the LoRA box weight must be a finite number >= 0, got {self.box_weight}")


@dataclass
class LoraBase:
    """The frozen model an adapter is trained on and the VAE whose latents it works in."""

    model: MultiViewDiT
    vae: SensorVAE
    vae_digest: str  # keys the run's latent cache
    file: Path  # the base weights' file, recorded in the adapter's metadata with its sha256
    file_sha256: str


def is_bundle(path: str | Path | None) -> bool:
    return path is not None and (Path(path) / "manifest.json").is_file()


BUNDLE_MODELS = ("student", "reference")  # the DiTs of a bundle an adapter can be trained on


def bundle_model(base: str | Path | None) -> tuple[Path, str] | None:
    """(bundle, component) when ``base`` names a bundle's DiT: the bundle itself (its student) or
    its ``reference.safetensors`` / ``student.safetensors``; None otherwise."""
    if base is None:
        return None
    path = Path(base)
    if is_bundle(path):
        return path, "student"
    if path.suffix == ".safetensors" and path.stem in BUNDLE_MODELS and is_bundle(path.parent):
        return path.parent, path.stem
    return None


def load_lora_base(base: str | Path | None, run_dir: Path, cfg: ModelConfig | None = None) -> LoraBase:
    """``base``: None (``run_dir/teacher/model`` with ``run_dir/vae``), an exported DiT (with
    ``run_dir/vae``), or a checkpoint bundle's DiT (:func:`bundle_model`: its student by default,
    ``BUNDLE/reference.safetensors`` for its reference model), upcast exactly to float32, with the
    bundle's VAE. ``cfg``: the run's config the base must share sensors, VAE and controls with
    (None: the base's). Raises ``FileNotFoundError``/``ValueError`` saying what to train or pass instead."""
    in_bundle = bundle_model(base)
    if in_bundle is not None:
        from world_model.rollout.runtime import load_world_model

        bundle, component = in_bundle
        wm = load_world_model(bundle, dtype="float32")
        model, vae = getattr(wm, component), wm.vae
        if model is None:
            raise FileNotFoundError(f"the bundle {bundle} has no {component} model")
        components = json.loads((bundle / "manifest.json").read_text())["components"]  # verified by the load
        digest = encoder_digest(vae)
        file, file_sha256 = bundle / components[component]["file"], components[component]["sha256"]
    else:
        base_path = Path(base).with_suffix("") if base else run_dir / "teacher" / EXPORT
        if not base_path.with_suffix(".safetensors").exists():
            raise FileNotFoundError(
                f"--stage lora adapts {base_path}.safetensors, which does not exist; "
                "run --stage teacher first, or pass --base (an exported DiT or a checkpoint bundle)"
            )
        model = load_teacher(base_path)
        vae, digest = run_vae(run_dir, cfg or model.cfg, "lora")
        file = base_path.with_suffix(".safetensors")
        file_sha256 = sha256_file(file)
    if cfg is not None and model.cfg.shared_settings() != cfg.shared_settings():  # teacher, student or reference model
        raise ValueError(f"the base model {file} has preset {model.cfg.name!r}'s config, not {cfg.name!r}'s")
    return LoraBase(model, vae, digest, file, file_sha256)


@dataclass(frozen=True, kw_only=True)
class LoraStageOptions(StageOptions):
    """The ``lora`` stage's options: :class:`StageOptions` and the adapter's, checked when made,
    before anything is written.

    ``case`` names the adapter (and the rare category), ``case_data`` an extra dataset of rare
    clips, ``case_clips`` explicit rare clip names, ``base`` the model adapted (default
    ``RUN/teacher/model``; module docstring), ``box_weight`` the extra loss weight inside the rare
    object's boxes (:attr:`LoraStageConfig.box_weight`), ``rank`` the adapter's rank (None:
    :class:`LoraConfig`'s)."""

    case: str | None = None
    case_data: str | Path | None = None
    case_clips: list[str] | None = None
    base: str | Path | None = None
    box_weight: float = 0.0
    rank: int | None = None

    def __post_init__(self) -> None:
        self.stage_config()
        lora_stage_dir(".", self.case)

    def stage_config(self) -> LoraStageConfig:
        """The adapter's training config: its box weight and rank."""
        lora = LoraConfig() if self.rank is None else LoraConfig().with_rank(self.rank)
        return LoraStageConfig(box_weight=self.box_weight, lora=lora)


def lora_setup(options: LoraStageOptions) -> dict:
    """The keyword arguments of :func:`lora_stage` from the stage's options."""
    return {
        "case": options.case,
        "case_data": options.case_data,
        "case_clips": options.case_clips,
        "base": options.base,
        "scfg": options.stage_config(),
    }


def lora_stage_dir(run_dir: str | Path, case: str | None) -> Path:
    """``run_dir/lora/<case>``; the case names the adapter."""
    from world_model.lora import _check_name

    if not case:
        raise ValueError("--stage lora needs --case NAME (the rare object category, e.g. tree_truck)")
    return Path(run_dir) / "lora" / _check_name(case)


def has_category(clip: Clip, category: str) -> bool:
    return any(o.category == category for fr in clip.frames for o in fr.objects)


class LoraBatch(NamedTuple):
    x0: torch.Tensor  # (B, T, V, C, h, w)
    cond: Conditions
    is_rare: np.ndarray  # (B,) bool
    weights: torch.Tensor | None  # (B, T, V, 1, h, w) loss weights (BalancedSampler.box_weights) or None
    spans: list[tuple[int, int]]  # (clip, start) of each window


class BalancedSampler:
    """Windows drawn ``rare_fraction`` of the time from the rare clips, else from the ordinary ones.

    ``windows`` holds all clips; ``rare``/``ordinary`` are clip indices into it.
    """

    def __init__(
        self, windows: LatentWindows, rare: list[int], ordinary: list[int], category: str, rare_fraction: float
    ) -> None:
        if not rare:
            raise ValueError(f"no rare-case clips: none contains an object of category {category!r}")
        if not ordinary and rare_fraction < 1.0:
            raise ValueError("no ordinary clips to balance the rare ones with; record a base dataset")
        if not 0.0 <= rare_fraction <= 1.0:
            raise ValueError(f"rare_fraction must be in [0, 1], got {rare_fraction}")
        self.windows, self.rare, self.ordinary, self.fraction = windows, rare, ordinary, rare_fraction
        self.category = category
        # Rare windows start where the rare object is present; fall back to every frame otherwise.
        self.rare_starts = {}
        for ci in rare:
            frames = windows.clips[ci].frames
            present = [f for f, fr in enumerate(frames) if any(o.category == category for o in fr.objects)]
            self.rare_starts[ci] = present or list(range(len(frames)))

    def draw(self, rng: np.random.Generator, batch: int, frames: int) -> tuple[list[tuple[int, int]], np.ndarray]:
        """``batch`` (clip, start) windows of ``frames`` frames and whether each is rare (B,) bool."""
        is_rare = rng.random(batch) < self.fraction
        out = []
        for rare in is_rare:
            if rare:
                pool = [(ci, s) for ci in self.rare for s in self.rare_starts[ci]]
            else:
                pool = [(ci, s) for ci in self.ordinary for s in range(self.windows.clips[ci].num_frames)]
            fits = [(ci, s) for ci, s in pool if s + frames <= self.windows.clips[ci].num_frames]
            if not fits:  # windows too long for this pool: start at frame 0 of its longest clip
                ci = max({ci for ci, _ in pool}, key=lambda i: self.windows.clips[i].num_frames)
                fits = [(ci, 0)]
            out.append(fits[int(rng.integers(len(fits)))])
        return out, is_rare

    def sample(self, rng: np.random.Generator, batch: int, box_weight: float = 0.0) -> LoraBatch:
        """A batch of windows; T from ``clip.train_frames``, weights from :meth:`box_weights`
        (None when ``box_weight`` is 0)."""
        t = int(rng.choice(self.windows.cfg.clip.train_frames))
        spans, is_rare = self.draw(rng, batch, t)
        t = min([t, *(self.windows.clips[ci].num_frames - s for ci, s in spans)])
        clips, starts = np.array([ci for ci, _ in spans]), np.array([s for _, s in spans])
        x0, cond = self.windows.windows(clips, starts, t)
        weights = None
        if box_weight > 0.0:
            weights = torch.stack([self.box_weights(ci, s, t, box_weight) for ci, s in spans])
        return LoraBatch(x0, cond, is_rare, weights, spans)

    def rare_region(self, clip: int, start: int, frames: int, rcfg: ReferenceConfig) -> np.ndarray:
        """(T, V, h, w) bool: the latent cells of the rare category's objects in one window."""
        frames_ = self.windows.clips[clip].frames[start : start + frames]
        return category_region(frames_, self.category, self.windows.cfg, rcfg)

    def box_weights(self, clip: int, start: int, frames: int, box_weight: float) -> torch.Tensor:
        """(T, V, 1, h, w) loss weights of one window: ``1 + box_weight`` on the latent cells of the
        rare category's objects (exact projected boxes), 1 elsewhere."""
        region = self.rare_region(clip, start, frames, ReferenceConfig(margin_px=0))
        return torch.from_numpy(np.where(region, 1.0 + box_weight, 1.0).astype(np.float32))[:, :, None]

    def reference_masks(self, rng: np.random.Generator, batch: LoraBatch, rcfg: ReferenceConfig) -> torch.Tensor:
        """(B, T, V, 1, h, w) observed-region masks for a reference-model base (module docstring):
        rare windows observe everything but the rare objects, ordinary ones draw from the task mix."""
        t = batch.x0.shape[1]
        masks = []
        for (ci, s), rare in zip(batch.spans, batch.is_rare, strict=True):
            if rare:
                masks.append((~self.rare_region(ci, s, t, rcfg))[:, :, None].astype(np.float32))
            else:
                task = TASKS[int(rng.choice(len(TASKS), p=rcfg.task_probs))]
                masks.append(task_mask(task, self.windows.cfg, self.windows.clips[ci].frames[s : s + t], rng, rcfg))
        return torch.from_numpy(np.stack(masks))


def select_clips(
    data_dir: Path, case_data: Path | None, cfg: ModelConfig, category: str, case_clips: list[str] | None
) -> tuple[list[Clip], list[int], list[int]]:
    """All clips, rare indices, ordinary indices (module docstring)."""
    base = load_clips(data_dir, cfg)
    extra = load_clips(case_data, cfg) if case_data is not None else []
    pool = extra or base
    if case_clips:
        names = {c.name for c in pool}
        missing = sorted(set(case_clips) - names)
        if missing:
            raise ValueError(f"case clips {missing} are not in {case_data or data_dir}")
        rare_clips = [c for c in pool if c.name in set(case_clips)]
    else:
        rare_clips = [c for c in pool if has_category(c, category)]
    rare_names = {c.name for c in rare_clips}
    ordinary = [c for c in base if c.name not in rare_names and not has_category(c, category)]
    clips = ordinary + rare_clips
    return clips, list(range(len(ordinary), len(clips))), list(range(len(ordinary)))


# Entries of the checkpoint's metadata a resumed run must share, each with the value a checkpoint
# without it was trained with: the loss, the frozen base (resuming on another base would silently
# train against the old one's weights, or fail on a shape), the adapter's shapes and the objective.
RESUME_KEYS = {"box_weight": 0.0, "base_sha256": None, "lora_rank": LoraConfig.rank, "reference_tasks": False}


def lora_stage(
    run: StageRun,
    *,
    case: str,
    case_data: str | Path | None = None,
    case_clips: list[str] | None = None,
    base: str | Path | None = None,
    scfg: LoraStageConfig | None = None,
) -> dict:
    """Train (or resume) adapter ``case`` on top of the frozen ``base`` (module docstring)."""
    scfg = scfg or LoraStageConfig()
    cfg, run_dir = run.cfg, run.run_dir
    lb = load_lora_base(base, run_dir, cfg)
    model = lb.model
    clips, rare, ordinary = select_clips(run.data_dir, Path(case_data) if case_data else None, cfg, case, case_clips)
    windows = latent_windows(clips, lb.vae, lb.vae_digest, run_dir, cfg, run.place.device)
    sampler = BalancedSampler(windows, rare, ordinary, case, scfg.rare_fraction)

    reference_tasks = bool(model.cfg.dit.in_channels_extra)  # a reference model: completion / the task mix
    fingerprint = base_fingerprint(model)
    torch.manual_seed(run.tcfg.seed)
    add_adapter(model, case, scfg.lora)
    model.train()
    meta = {
        "case": case,
        "base_sha256": fingerprint,
        "box_weight": scfg.box_weight,
        "lora_rank": scfg.lora.rank,
        "reference_tasks": reference_tasks,
        "model_config": model.cfg.to_dict(),
    }
    trainer = run.trainer(model, "lora", RESUME_KEYS, **meta)
    drawn = {"rare": 0, "ordinary": 0}
    summary = trainer.run(_lora_step(model, sampler, cfg, scfg, drawn), f"lora:{case}")
    ema = trainer.ema.model_state(model)
    # Only adapter tensors come from the EMA: the frozen base stays bit-identical.
    model.load_state_dict({k: v for k, v in ema.items() if ".lora_" in k}, strict=False)
    train_info = {
        "case": case,  # the rare category (the adapter may be renamed; lora.AdapterInfo.completes)
        "step": trainer.step,
        "rare_clips": [clips[i].name for i in rare],
        "ordinary_clips": len(ordinary),
        "rare_fraction": scfg.rare_fraction,
        "box_weight": scfg.box_weight,
        # a reference-model base: rare windows completed, ordinary ones the task mix
        "reference_tasks": reference_tasks,
    }
    adapter_meta = {
        "base_file": lb.file.name,  # the base is identified by its hashes; a path would name this machine
        "base_file_sha256": lb.file_sha256,
        "model_config": model.cfg.to_dict(),
        "train": train_info,
    }
    save_adapter(model, case, run.stage_dir, scfg.lora, fingerprint, adapter_meta)
    return {**summary, "drawn": drawn, "adapter_dir": str(run.stage_dir), "config": asdict(scfg)}


def _lora_step(
    model: MultiViewDiT, sampler: BalancedSampler, cfg: ModelConfig, scfg: LoraStageConfig, drawn: dict[str, int]
) -> StepFn:
    """The adapter's training step: a balanced batch (counted in ``drawn``), the base's
    flow-matching loss, weighted in the rare object's boxes; a reference-model base completes the
    rare objects or does the task mix (module docstring)."""
    extra_channels = model.cfg.dit.in_channels_extra
    rcfg = ReferenceConfig()

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        batch = sampler.sample(tr.rng, tr.tcfg.batch_size, scfg.box_weight)
        x0, is_rare = batch.x0, batch.is_rare
        drawn["rare"] += int(is_rare.sum())
        drawn["ordinary"] += int((~is_rare).sum())
        b = x0.shape[0]
        cond = tr.shard(batch.cond).with_drop(tr.shard(tr.rand(b) < cfg.flow.cond_drop_prob))
        t = tr.shard(sample_timesteps((b,), cfg.flow, tr.gen))
        noise = tr.shard(tr.randn(*x0.shape))
        weights = None if batch.weights is None else tr.shard(batch.weights)
        if extra_channels:  # a reference model: completion of the rare objects / the task mix
            extra = tr.shard(reference_input(x0, sampler.reference_masks(tr.rng, batch, rcfg)))
            x0 = tr.shard(x0)
            loss = flow_matching_loss(
                lambda xt, tt: model(torch.cat([xt, extra], dim=3), tt, cond), x0, t, noise, weights
            )
        else:
            x0 = tr.shard(x0)
            loss = flow_matching_loss(lambda xt, tt: model(xt, tt, cond), x0, t, noise, weights)
        return loss, b * x0.shape[1]

    return step
