"""A trained world model: load a checkpoint bundle into the modules that stream rollouts.

    wm = load_world_model()                        # the shipped default bundle (or a path)

:class:`WorldModel` holds the VAE, the causal student, the reference model and what turns
SceneFrames into their conditions (:class:`~world_model.rollout.builder.ConditionBuilder`); it
samples first frames and decodes latents. Streaming many rollouts through it:
:mod:`world_model.rollout.batch`.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from world_model.bundle import CheckpointError, load_bundle_files, save_bundle, streaming_config
from world_model.lora import loaded_adapters, only_adapters
from world_model.model.conditions import Conditions
from world_model.model.config import ModelConfig, with_student_settings
from world_model.model.dit import MultiViewDiT
from world_model.model.imagedesc import VaeCropEncoder
from world_model.model.reference import ReferenceGenerator, first_frame_sampling, reference_model_config
from world_model.model.rows import split_rows
from world_model.model.sampler import DECODE_FRAMES_PER_CALL, latents_to_observations
from world_model.model.text import TextEncoder, make_text_encoder
from world_model.model.vae import SensorVAE
from world_model.observation import ALL_SENSORS, Observation, SensorSelection
from world_model.precision import check_dtype, dit_precision, resolve_bf16, resolve_device
from world_model.rollout.builder import ConditionBuilder
from world_model.scene import CATEGORIES, SceneFrame
from world_model.sensors import CameraRig
from world_model.streaming import StreamingConfig, StreamingConfigError
from world_model.student.config import StudentConfig

__all__ = ["WorldModel", "load_world_model", "save_untrained_bundle"]


@dataclass
class WorldModel:
    """The modules of one bundle, in eval mode, plus what turns SceneFrames into their conditions."""

    cfg: ModelConfig
    student_cfg: StudentConfig
    vae: SensorVAE
    student: MultiViewDiT
    reference: MultiViewDiT | None
    text: TextEncoder
    path: Path | None = None
    streaming: StreamingConfig = field(default_factory=StreamingConfig)  # the bundle's streaming.json
    first_frame: MultiViewDiT | None = None  # the one-step first-frame model, when the bundle has one

    def __post_init__(self) -> None:
        self.image = VaeCropEncoder(self.vae)
        self.rig: CameraRig = self.cfg.sensors.rig()
        self.conditions = ConditionBuilder(self.cfg, self.text, self.image)
        self.first_frames = ReferenceGenerator(self.reference or self.student, self.vae)
        self.one_step_frames = None if self.first_frame is None else ReferenceGenerator(self.first_frame, self.vae)
        self._adapter_dirs: dict[tuple[str, str], Path] = {}  # (model, adapter name) -> its directory
        self._completion: dict[str, str] = {}  # reference-model completion adapter -> the category it completes
        # First frames switch the reference model's adapters on and off around a completion: one
        # at a time when rollouts start on several threads (world_model.rollout.shards).
        self._switching = threading.Lock()

    def _switching_adapters(self, completion: Mapping[str, str]) -> AbstractContextManager:
        """Held while the reference model's adapters are switched for ``completion`` (none: nothing)."""
        return self._switching if completion else nullcontext()

    @property
    def dtype(self) -> str:
        """The DiTs' precision (and the camera decoder's): "bfloat16" or "float32"."""
        return "bfloat16" if self.cfg.dit.autocast_bf16 else "float32"

    @property
    def adapter_dirs(self) -> list[Path]:
        """The directories of the adapters :meth:`apply_adapters` loaded, in loading order."""
        return list(self._adapter_dirs.values())

    def apply_adapters(self, names: Sequence[str | Path]) -> list[str]:
        """Load LoRA adapters (§5), each into the model it was trained on: the student (every
        chunk) or the reference model (first frames; adapters of ``--stage lora --base
        RUN/reference/model``), matched by base fingerprint. A reference-model adapter trained in
        the completion task (:attr:`world_model.lora.AdapterInfo.completes`) acts only where
        :meth:`first_frame` completes its category. All are matched before any is loaded,
        so a refused list leaves the models as they were; an adapter already loaded from the same
        directory is skipped, another one under a loaded name is refused. Names are looked up in
        the bundle's ``adapters/`` folder, ``$M4WORLD_ADAPTERS`` and the package; paths are used as
        given. Returns the names loaded in the student, then those in the reference model.
        Raises ``AdapterMismatchError`` for an adapter that fits neither model."""
        from world_model.lora import (
            META,
            AdapterMismatchError,
            apply_adapters,
            base_fingerprint,
            loaded_adapters,
            read_adapter,
            resolve_adapter,
        )

        search = [self.path / "adapters"] if self.path is not None else []
        models = {"student": self.student}
        if self.reference is not None:
            models["reference model"] = self.reference
        prints = {label: base_fingerprint(model) for label, model in models.items()}
        plan: list[tuple[str, str, Path]] = []  # (model label, adapter name, directory)
        for item in names:
            path = resolve_adapter(item, search).resolve()
            info, _ = read_adapter(path)
            label = next((lb for lb, fp in prints.items() if fp == info.base_sha256), None)
            if label is None:
                ours = ", ".join(f"the {lb}'s {fp[:16]}…" for lb, fp in prints.items())
                raise AdapterMismatchError(
                    f"adapter {info.name!r} ({path}) was trained on base weights {info.base_sha256[:16]}…, "
                    f"none of this checkpoint's models ({ours}); retrain it with --base pointing at one of them"
                )
            if label == "reference model" and info.completes and info.completes not in CATEGORIES:
                raise ValueError(
                    f"completion adapter {info.name!r} ({path}) names no object category it completes "
                    f"({info.completes!r} is not one of {CATEGORIES}); set train.case in its {META}"
                )
            loaded = self._adapter_dirs.get((label, info.name))
            if loaded is not None and loaded != path:
                raise ValueError(f"the {label} already has an adapter named {info.name!r}, from {loaded}, not {path}")
            plan.append((label, info, path))
        for label, info, path in plan:
            if (label, info.name) not in self._adapter_dirs:
                apply_adapters(models[label], [path])
                self._adapter_dirs[(label, info.name)] = path
                if label == "reference model" and info.completes:
                    self._completion[info.name] = info.completes
        return [name for model in models.values() for name in loaded_adapters(model)]

    @torch.no_grad()
    def first_latents(
        self,
        cond: Conditions,
        frame: SceneFrame,
        reference: Mapping[str, np.ndarray] | None = None,
        seed: int = 0,
    ) -> torch.Tensor:
        """A rollout's first frame (batch 1): latents (1, 1, V, C, h, w), to decode with
        :meth:`decode` (with ``cond``'s first frame's decoder inputs).

        From controls (``reference`` None: by the bundle's one-step first-frame model where
        :meth:`_first_frame_sampling` picks it) or anchored on the user's images (§6), by the
        reference model without its completion adapters. Then, for a frame generated from
        controls, each completion adapter whose category is in ``frame`` regenerates that
        category's projected boxes with the rest of the frame observed (task (c), what the adapter
        was trained for): the rare object is drawn into its box, the scene around it, and every
        frame without the category, stay exactly what the base model drew. A user's images are
        kept as given."""
        gen = self.first_frames
        steps, guidance = self.streaming.first_frame_steps, self.streaming.first_frame_guidance
        model = gen.model
        loaded = loaded_adapters(model)
        completion = {n: c for n, c in self._completion.items() if n in loaded}  # not removed since
        others = [n for n in loaded if n not in completion]
        with self._switching_adapters(completion):
            with only_adapters(model, others) if completion else nullcontext():  # no switching without one
                if reference:
                    latents = gen.first_latents(cond, reference, steps, seed, guidance=guidance)
                else:
                    sampler, how = self._first_frame_sampling(others)
                    latents = sampler.sample(cond.frames(0, 1), seed=seed, **how)
            wanted = {n: c for n, c in completion.items() if any(o.category == c for o in frame.objects)}
            if reference or not wanted:
                return latents
            for name, category in wanted.items():
                with only_adapters(model, [*others, name]):
                    latents = gen.complete_category(cond, latents, [frame], category, steps, seed, guidance=guidance)
        return latents

    @torch.no_grad()
    def batch_first_latents(self, cond: Conditions, frames: Sequence[SceneFrame], seeds: Sequence[int]) -> torch.Tensor:
        """First frames' latents (R, 1, V, C, h, w) of ``len(frames)`` rollouts from controls, row i
        exactly ``first_latents(cond row i, frames[i], seed=seeds[i])``. One batched call of the
        first-frame or reference model (computed row-independently on CPU, :mod:`world_model.model.rows`),
        unless a completion adapter redraws a category in one of the frames: then one call per row."""
        if cond.batch_size != len(frames) or len(seeds) != len(frames):
            raise ValueError(f"need one frame and one seed per row of cond ({cond.batch_size})")
        gen = self.first_frames
        loaded = loaded_adapters(gen.model)
        completion = {n: c for n, c in self._completion.items() if n in loaded}
        if any(o.category in completion.values() for f in frames for o in f.objects):
            return torch.cat(
                [
                    self.first_latents(cond.apply(lambda _, v, i=i: v[i : i + 1]), f, seed=s)
                    for i, (f, s) in enumerate(zip(frames, seeds, strict=True))
                ]
            )
        others = [n for n in loaded if n not in completion]
        on_cpu = next(gen.model.parameters()).device.type == "cpu"
        rowwise = split_rows(len(frames)) if on_cpu else nullcontext()
        switched = only_adapters(gen.model, others) if completion else nullcontext()
        sampler, how = self._first_frame_sampling(others)
        with self._switching_adapters(completion), switched, rowwise:
            return sampler.sample(cond.frames(0, 1), seed=[int(s) for s in seeds], **how)

    def _first_frame_sampling(self, others: Sequence[str]) -> tuple[ReferenceGenerator, dict[str, Any]]:
        """:func:`~world_model.model.reference.first_frame_sampling` of this bundle: the one-step
        first-frame model only while the reference model has no adapter in use (``others``; the
        first-frame model has none)."""
        return first_frame_sampling(self.first_frames, None if others else self.one_step_frames, self.streaming)

    def decode(
        self,
        latents: torch.Tensor,
        labels: torch.Tensor | np.ndarray | None = None,
        style: torch.Tensor | np.ndarray | None = None,
        nearness: torch.Tensor | np.ndarray | None = None,
        sensors: SensorSelection = ALL_SENSORS,
        range_nearness: torch.Tensor | np.ndarray | None = None,
        precipitation: torch.Tensor | np.ndarray | None = None,
        precipitation_rgb: torch.Tensor | np.ndarray | None = None,
    ) -> list[list[Observation]]:
        """(B, T, V, C, h, w) normalized latents → B lists of T observations of the ``sensors``
        decoded (the others None); ``labels`` (B, T, Vc, 3, H, W)
        the frames' camera label maps, ``style`` (B, Dt) the scenes' styles and ``nearness`` (B, T, H, W)
        the LiDAR view's nearness maps, for a decoder that draws them (``ConditionArrays.labels``,
        ``ConditionArrays.style``, ``ConditionArrays.lidar_nearness``); ``range_nearness``
        (B, T, beams, azimuth) the same at the range map's resolution, for a VAE with a range head
        (``ConditionArrays.range_nearness``); ``precipitation`` (B, T, Vc, H, W) and
        ``precipitation_rgb`` (B, T, 3) the rain or snow blended over the cameras
        (``ConditionArrays.precipitation``).

        On CPU each frame is decoded alone: the decoder's convolutions and group norms pick other
        kernels and reduction splits for another batch size (up to 1e-5 m of LiDAR apart,
        ``m4world bench row_independence``), so a batched decode would make a vector env's row
        differ from the same rollout run alone; it costs ~10% of the decode at 64 frames. On a GPU,
        where the student is batched too (no bit-for-bit promise there), frames go
        :data:`DECODE_FRAMES_PER_CALL` at a time: one call per frame would launch the decoder's
        kernels once per env."""
        on_cpu = next(self.vae.parameters()).device.type == "cpu"
        return latents_to_observations(
            self.vae,
            latents,
            self.cfg.sensors.lidar,
            frames_per_call=1 if on_cpu else DECODE_FRAMES_PER_CALL,
            labels=labels,
            style=style,
            nearness=nearness,
            sensors=sensors,
            range_nearness=range_nearness,
            precipitation=precipitation,
            precipitation_rgb=precipitation_rgb,
        )


def load_world_model(
    path: str | Path | None = None,
    student: StudentConfig | None = None,
    device: str | torch.device = "cpu",
    dtype: str = "auto",
    context_frames: int | None = None,
) -> WorldModel:
    """Load and verify a checkpoint bundle (default: the shipped one), streaming as its
    ``streaming.json`` says. ``student`` replaces the student's settings, streaming included. ``dtype`` of the
    DiTs: "auto" (bf16 when the checkpoint was trained with ``dit.autocast_bf16`` and ``device``
    multiplies bf16 faster than float32, else float32: :func:`world_model.precision.resolve_bf16`),
    "float32" or "bfloat16". ``context_frames`` runs the student with another rolling window than
    the one it was trained with (None: the bundle's ``clip.context_frames``): a study knob."""
    check_dtype(dtype)
    device = resolve_device(device)
    if context_frames is not None and context_frames < 1:  # here: in the try below it would read as a bad bundle
        raise ValueError(f"context_frames must be >= 1, got {context_frames}")
    files = load_bundle_files(path)
    try:
        streaming = streaming_config(files.path, files.streaming)
    except StreamingConfigError as e:  # a setting out of bounds, named by the file's path and key
        raise CheckpointError(str(e)) from e
    try:
        cfg = ModelConfig.from_dict(files.model_config)
        cfg = with_student_settings(cfg.with_depth(cfg.dit.depth), context_frames=context_frames)  # the student's
        own = files.component_config("reference") if files.has("reference") else None
        ref_cfg = reference_model_config(cfg) if own is None else ModelConfig.from_dict(own)
        if ref_cfg.shared_settings() != cfg.shared_settings():
            raise ValueError("the reference model's sensors, VAE or controls differ from the student's")
        first_own = files.component_config("first_frame") if files.has("first_frame") else None
        if first_own is not None and ModelConfig.from_dict(first_own) != ref_cfg:
            raise ValueError("the first-frame model's config differs from the reference model's")
        bf16 = resolve_bf16(dtype, cfg.dit.autocast_bf16, device)
        cfg, ref_cfg = (replace(c, dit=replace(c.dit, autocast_bf16=bf16)) for c in (cfg, ref_cfg))
        trained = StudentConfig.from_dict(files.manifest.get("student_config", {}))
        scfg = student or replace(trained, streaming=streaming)
        vae = SensorVAE(cfg)
        vae.load_state_dict(files.tensors["vae"])
        with dit_precision(bf16):  # the weights' dtype below, whatever precision context encloses the load
            dit = MultiViewDiT(cfg)
            ref = MultiViewDiT(ref_cfg) if files.has("reference") else None
            first = MultiViewDiT(ref_cfg) if files.has("first_frame") else None  # a reference model's copy
        dit.load_state_dict(files.tensors["student"])
        for module, component in ((ref, "reference"), (first, "first_frame")):
            if module is not None:
                module.load_state_dict(files.tensors[component])
    except (KeyError, RuntimeError, TypeError, ValueError) as e:
        raise CheckpointError(f"checkpoint {files.path} does not match this version of the model: {e}") from e
    for module in (vae, dit, ref, first):
        if module is not None:
            module.to(device).eval().requires_grad_(False)
    if cfg.dit.autocast_bf16:
        # Weights kept in bf16 once, instead of autocast re-casting them at every call (~15% of a step).
        for module in (dit, ref, first):
            if module is not None:
                module.to(torch.bfloat16)
    return WorldModel(cfg, scfg, vae, dit, ref, make_text_encoder(cfg.text), files.path, streaming, first)


def save_untrained_bundle(
    out_dir: str | Path, preset: str = "tiny", seed: int = 0, geometry_only: bool = False, layout: bool = False
) -> Path:
    """A bundle of freshly initialized modules of ``preset`` (with pixel-aligned layout
    conditioning when ``layout``): exercises every code path of the world-model backend (shapes,
    seeding, batching, memory) without training; outputs are noise."""
    from world_model.model.config import get_preset, with_layout

    cfg = with_layout(get_preset(preset, geometry_only=geometry_only), layout)
    student_cfg, ref_cfg = cfg.for_student(), reference_model_config(cfg)
    torch.manual_seed(seed)
    parts = {
        "vae": SensorVAE(cfg).state_dict(),
        "student": MultiViewDiT(student_cfg).state_dict(),
        "reference": MultiViewDiT(ref_cfg).state_dict(),
    }
    stages = {k: "untrained" for k in parts}
    return save_bundle(
        out_dir, student_cfg.to_dict(), parts, stages=stages, component_configs={"reference": ref_cfg.to_dict()}
    )
