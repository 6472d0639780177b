"""Run a trained world model: load a checkpoint bundle and stream batched rollouts from SceneFrames.

    wm = load_world_model()                        # the shipped default bundle (or a path)
    rollouts = RolloutBatch(wm, num_rollouts=8)
    obs0 = rollouts.reset_row(0, first_frame, seed=0)          # first frame via the reference model (§6)
    obs = rollouts.step([chunk_0, ..., chunk_7])               # one causal chunk per rollout (§4.2)

Each rollout owns a ``torch.Generator`` seeded at its reset, and every noise tensor of that rollout
(first frame, every chunk, every re-noising) is drawn from it, so a rollout's observations do not
depend on which other rollouts share its batch: a vector env equals N single envs.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Mapping, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch

from world_model.bundle import CheckpointError, load_bundle_files, save_bundle  # noqa: F401 (re-export)
from world_model.conditioning import ConditionBuilder
from world_model.lora import loaded_adapters, only_adapters
from world_model.model.conditions import ConditionArrays, Conditions
from world_model.model.config import ModelConfig, with_student_settings
from world_model.model.dit import MultiViewDiT
from world_model.model.imagedesc import VaeCropEncoder
from world_model.model.reference import ReferenceGenerator, reference_model_config
from world_model.model.rows import split_rows
from world_model.model.sampler import DECODE_FRAMES_PER_CALL, latents_to_observations
from world_model.model.text import TextEncoder, make_text_encoder
from world_model.model.vae import SensorVAE
from world_model.observation import Observation
from world_model.precision import check_dtype, dit_precision, resolve_bf16, resolve_device
from world_model.scene import CATEGORIES, SceneFrame
from world_model.sensors import CameraRig
from world_model.sim.labels import CLASS_PLANE, NO_LABEL
from world_model.streaming import STREAMING_FILE, StreamingConfig, StreamingConfigError
from world_model.student.config import StudentConfig
from world_model.student.engine import StreamingEngine

__all__ = ["RolloutBatch", "WorldModel", "load_world_model", "save_bundle", "save_untrained_bundle"]


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

    def __post_init__(self) -> None:
        self.image = VaeCropEncoder(self.vae)
        self.rig: CameraRig = self.cfg.sensors.rig()
        self.conditions = ConditionBuilder(self.cfg, self.text, self.image)
        self.first_frames = ReferenceGenerator(self.reference or self.student, self.vae)
        self._adapter_dirs: dict[tuple[str, str], Path] = {}  # (model, adapter name) -> its directory
        self._completion: dict[str, str] = {}  # reference-model completion adapter -> the category it completes

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
    def first_frame(
        self, cond: Conditions, frame: SceneFrame, reference: Mapping[str, np.ndarray] | None = None, seed: int = 0
    ) -> tuple[torch.Tensor, Observation]:
        """A rollout's first frame (batch 1): latents (1, 1, V, C, h, w) and its observation.

        From controls (``reference`` None) or anchored on the user's images (§6), by the
        reference model without its completion adapters. Then, for a frame generated from
        controls, each completion adapter whose category is in ``frame`` regenerates that
        category's projected boxes with the rest of the frame observed (task (c), what the adapter
        was trained for): the rare object is drawn into its box, the scene around it, and every
        frame without the category, stay exactly what the base model drew. A user's images are
        kept as given."""
        gen = self.first_frames
        model = gen.model
        loaded = loaded_adapters(model)
        completion = {n: c for n, c in self._completion.items() if n in loaded}  # not removed since
        others = [n for n in loaded if n not in completion]
        with only_adapters(model, others) if completion else nullcontext():  # no switching without one
            latents, obs = gen.first_frame(cond, reference, seed=seed)
        wanted = {n: c for n, c in completion.items() if any(o.category == c for o in frame.objects)}
        if reference or not wanted:
            return latents, obs[0]
        for name, category in wanted.items():
            with only_adapters(model, [*others, name]):
                latents = gen.complete_category(cond, latents, [frame], category, seed=seed)
        return latents, self.decode(latents, **cond.frames(0, 1).decoder_inputs())[0][0]

    @torch.no_grad()
    def batch_first_frames(
        self, cond: Conditions, frames: Sequence[SceneFrame], seeds: Sequence[int]
    ) -> tuple[torch.Tensor, list[Observation]]:
        """First frames of ``len(frames)`` rollouts from controls, row i exactly
        ``first_frame(cond row i, frames[i], seed=seeds[i])``: latents (R, 1, V, C, h, w) and R
        observations. One batched reference-model call (computed row-independently on CPU,
        :mod:`world_model.model.rows`), unless a completion adapter redraws a category in one of
        the frames: then one call per row."""
        if cond.batch_size != len(frames) or len(seeds) != len(frames):
            raise ValueError(f"need one frame and one seed per row of cond ({cond.batch_size})")
        gen = self.first_frames
        loaded = loaded_adapters(gen.model)
        completion = {n: c for n, c in self._completion.items() if n in loaded}
        if any(o.category in completion.values() for f in frames for o in f.objects):
            pairs = [
                self.first_frame(cond.apply(lambda _, v, i=i: v[i : i + 1]), f, seed=s)
                for i, (f, s) in enumerate(zip(frames, seeds, strict=True))
            ]
            return torch.cat([lat for lat, _ in pairs]), [obs for _, obs in pairs]
        others = [n for n in loaded if n not in completion]
        on_cpu = next(gen.model.parameters()).device.type == "cpu"
        rowwise = split_rows(len(frames)) if on_cpu else nullcontext()
        with only_adapters(gen.model, others) if completion else nullcontext(), rowwise:
            latents = gen.sample(cond.frames(0, 1), seed=[int(s) for s in seeds])
        return latents, [obs[0] for obs in self.decode(latents, **cond.frames(0, 1).decoder_inputs())]

    def decode(
        self,
        latents: torch.Tensor,
        labels: torch.Tensor | np.ndarray | None = None,
        style: torch.Tensor | np.ndarray | None = None,
        nearness: torch.Tensor | np.ndarray | None = None,
    ) -> list[list[Observation]]:
        """(B, T, V, C, h, w) normalized latents → B lists of T observations; ``labels`` (B, T, Vc, 3, H, W)
        the frames' camera label maps, ``style`` (B, Dt) the scenes' styles and ``nearness`` (B, T, H, W)
        the LiDAR view's nearness maps, for a decoder that draws them (``ConditionArrays.labels``,
        ``ConditionArrays.style``, ``ConditionArrays.lidar_nearness``).

        On CPU each frame is decoded alone: the decoder's convolutions and group norms pick other
        kernels and reduction splits for another batch size (up to 1e-5 m of LiDAR apart,
        ``benchmarks/row_independence.py``), so a batched decode would make a vector env's row
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
    computes bf16 natively, else float32: :func:`world_model.precision.resolve_bf16`),
    "float32" or "bfloat16". ``context_frames`` runs the student with another rolling window than
    the one it was trained with (None: the bundle's ``clip.context_frames``): a study knob."""
    check_dtype(dtype)
    device = resolve_device(device)
    if context_frames is not None and context_frames < 1:  # here: in the try below it would read as a bad bundle
        raise ValueError(f"context_frames must be >= 1, got {context_frames}")
    files = load_bundle_files(path)
    try:
        streaming = StreamingConfig.from_dict(files.streaming or {}, f"{files.path / STREAMING_FILE}")
    except StreamingConfigError as e:  # a setting out of bounds, named by the file's path and key
        raise CheckpointError(str(e)) from e
    try:
        cfg = ModelConfig.from_dict(files.model_config)
        cfg = with_student_settings(cfg.with_depth(cfg.dit.depth), context_frames=context_frames)  # the student's
        own = files.component_config("reference") if files.has("reference") else None
        ref_cfg = reference_model_config(cfg) if own is None else ModelConfig.from_dict(own)
        if ref_cfg.shared_settings() != cfg.shared_settings():
            raise ValueError("the reference model's sensors, VAE or controls differ from the student's")
        bf16 = resolve_bf16(dtype, cfg.dit.autocast_bf16, device)
        cfg, ref_cfg = (replace(c, dit=replace(c.dit, autocast_bf16=bf16)) for c in (cfg, ref_cfg))
        trained = StudentConfig.from_dict(files.manifest.get("student_config", {}))
        scfg = student or replace(trained, streaming=streaming)
        vae = SensorVAE(cfg)
        vae.load_state_dict(files.tensors["vae"])
        with dit_precision(bf16):  # the weights' dtype below, whatever precision context encloses the load
            dit = MultiViewDiT(cfg)
            ref = MultiViewDiT(ref_cfg) if files.has("reference") else None
        dit.load_state_dict(files.tensors["student"])
        if ref is not None:
            ref.load_state_dict(files.tensors["reference"])
    except (KeyError, RuntimeError, TypeError, ValueError) as e:
        raise CheckpointError(f"checkpoint {files.path} does not match this version of the model: {e}") from e
    for module in (vae, dit, ref):
        if module is not None:
            module.to(device).eval().requires_grad_(False)
    if cfg.dit.autocast_bf16:
        # Weights kept in bf16 once, instead of autocast re-casting them at every call (~15% of a step).
        for module in (dit, ref):
            if module is not None:
                module.to(torch.bfloat16)
    return WorldModel(cfg, scfg, vae, dit, ref, make_text_encoder(cfg.text), files.path, streaming)


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


def start_key(arrays: ConditionArrays, seed: int, frame: SceneFrame) -> bytes:
    """A digest of a rollout's first-frame condition arrays, seed and the categories of the frame's
    objects (a completion adapter redraws a frame by those): rollouts with equal keys start from
    the same first frame."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(int(seed).to_bytes(8, "little", signed=True))
    digest.update(",".join(sorted(o.category for o in frame.objects)).encode())
    for f in fields(arrays):
        value = np.ascontiguousarray(getattr(arrays, f.name))
        digest.update(f"{f.name}:{value.dtype}:{value.shape}".encode())
        digest.update(value.tobytes())
    return digest.digest()


class RolloutBatch:
    """``num_rollouts`` independent rollouts advanced together, one causal chunk per :meth:`step`."""

    def __init__(self, wm: WorldModel, num_rollouts: int, every_frame: bool = False) -> None:
        self.wm = wm
        self.n = num_rollouts
        self.every_frame = every_frame
        self.engine = StreamingEngine(wm.student, wm.student_cfg, generator=self._noise)
        self.gens: list[torch.Generator | None] = [None] * num_rollouts
        self.first: list[SceneFrame | None] = [None] * num_rollouts
        # Per rollout: reference crops by track id, and the frame index each applies from.
        self.crops: list[dict[str, np.ndarray]] = [{} for _ in range(num_rollouts)]
        self.crop_since: list[dict[str, int]] = [{} for _ in range(num_rollouts)]
        self.last_arrays: list[ConditionArrays | None] = [None] * num_rollouts
        self._pending: dict[int, tuple[torch.Tensor, ConditionArrays]] = {}
        # Wall seconds spent by step() building conditions (BEV raster, text, crops: outside the
        # networks), in the student and in VAE decoding; benchmarks read and reset them.
        self.seconds = {"conditions": 0.0, "student": 0.0, "decode": 0.0}

    @property
    def chunk_frames(self) -> int:
        return self.wm.cfg.clip.chunk_frames

    def _row_independent(self) -> AbstractContextManager:
        """Batched student calls computed row for row as a batch of one would on CPU
        (:mod:`world_model.model.rows`), so a rollout never depends on the others in its batch."""
        return split_rows(self.n) if self._on_cpu else nullcontext()

    @property
    def _device(self) -> torch.device:
        return next(self.wm.student.parameters()).device

    @property
    def _on_cpu(self) -> bool:
        return self._device.type == "cpu"

    def _finish_device_work(self) -> None:
        """Wait for the student's kernels on an asynchronous device (CUDA), so that ``seconds``
        charges them to the student rather than to the decoder's first read of its latents."""
        if self._device.type == "cuda":
            torch.cuda.synchronize(self._device)

    def _noise(self, shape: Sequence[int]) -> torch.Tensor:
        """Batch noise, each row from its own rollout's (CPU) generator; the engine moves it to the
        model's device, so a seed gives the same rollout noise on every device."""
        return torch.stack([torch.randn(tuple(shape[1:]), generator=g) for g in self.gens])

    def reset_row(
        self,
        row: int,
        frame: SceneFrame,
        seed: int,
        reference: Mapping[str, np.ndarray] | None = None,
        crops: Mapping[str, np.ndarray] | None = None,
        crop_since: Mapping[str, int] | None = None,
    ) -> Observation:
        """(Re)start rollout ``row`` at ``frame``: its first frame comes from the reference model,
        anchored on ``reference`` images when given (§6), and seeds the student's cache. ``crops``
        and ``crop_since``: as :meth:`ConditionBuilder.arrays`; set ``self.crops[row]`` and
        ``self.crop_since[row]`` between steps as new crops are cut."""
        self.crops[row], self.crop_since[row] = dict(crops or {}), dict(crop_since or {})
        arrays = self.wm.conditions.arrays([frame], frame, self.crops[row], self.crop_since[row])
        return self.start_row(row, frame, seed, arrays, reference)

    def start_row(
        self,
        row: int,
        frame: SceneFrame,
        seed: int,
        arrays: ConditionArrays,
        reference: Mapping[str, np.ndarray] | None = None,
    ) -> Observation:
        """:meth:`reset_row` given the first frame's condition arrays, built by the caller."""
        self.gens[row] = torch.Generator().manual_seed(int(seed))
        self.first[row] = frame
        with torch.no_grad():
            latents, obs = self.wm.first_frame(Conditions.collate([arrays]), frame, reference, seed=int(seed))
        self._start([row], latents, [arrays])
        return obs

    def reset_rows(
        self,
        rows: Sequence[int],
        frames: Sequence[SceneFrame],
        seeds: Sequence[int],
        crops: Sequence[Mapping[str, np.ndarray] | None] | None = None,
        crop_since: Sequence[Mapping[str, int] | None] | None = None,
    ) -> list[Observation]:
        """:meth:`reset_row` of several rows from controls, their first frames sampled in one
        batched reference-model call (:meth:`WorldModel.batch_first_frames`); each row exactly as
        its own :meth:`reset_row` would be. ``crops`` and ``crop_since``: one per row, or None."""
        crops = list(crops) if crops is not None else [None] * len(rows)
        since = list(crop_since) if crop_since is not None else [None] * len(rows)
        if not len(rows) == len(frames) == len(seeds) == len(crops) == len(since) or len(set(rows)) != len(rows):
            raise ValueError(f"need distinct rows and one frame, seed and crops per row, got rows {list(rows)}")
        arrays = []
        for row, frame, crop, first_seen in zip(rows, frames, crops, since, strict=True):
            self.crops[row], self.crop_since[row] = dict(crop or {}), dict(first_seen or {})
            arrays.append(self.wm.conditions.arrays([frame], frame, self.crops[row], self.crop_since[row]))
        return self.start_rows(rows, frames, seeds, arrays)

    def start_rows(
        self,
        rows: Sequence[int],
        frames: Sequence[SceneFrame],
        seeds: Sequence[int],
        arrays: Sequence[ConditionArrays],
    ) -> list[Observation]:
        """:meth:`reset_rows` given each row's first-frame condition arrays, built by the caller."""
        if not len(rows) == len(frames) == len(seeds) == len(arrays) or len(set(rows)) != len(rows):
            raise ValueError(f"need distinct rows and one frame, seed and arrays per row, got rows {list(rows)}")
        for row, frame, seed in zip(rows, frames, seeds, strict=True):
            self.gens[row] = torch.Generator().manual_seed(int(seed))
            self.first[row] = frame
        # Rows that start from the same controls and seed (one scene and seed under several
        # policies) get the same first frame: it is sampled once and copied (on CPU bit for bit
        # what each row's own call gives; on a GPU the smaller batch may round differently).
        keys = [start_key(a, s, f) for a, s, f in zip(arrays, seeds, frames, strict=True)]
        unique = list(dict.fromkeys(keys))
        firsts = [keys.index(k) for k in unique]
        latents, obs = self.wm.batch_first_frames(
            Conditions.collate([arrays[i] for i in firsts]),
            [frames[i] for i in firsts],
            [int(seeds[i]) for i in firsts],
        )
        source = [unique.index(k) for k in keys]
        latents = latents[source]
        obs = [replace(obs[j], cameras=obs[j].cameras.copy(), lidar=obs[j].lidar.copy()) for j in source]
        self._start(list(rows), latents, list(arrays))
        return obs

    def _start(self, rows: list[int], latents: torch.Tensor, arrays: list[ConditionArrays]) -> None:
        """Seed the student's cache of ``rows`` with their first frames (R, 1, V, C, h, w)."""
        for row, a in zip(rows, arrays, strict=True):
            self.last_arrays[row] = a
        if self.engine.batch_size == self.n and self.n > 1:
            with torch.no_grad(), split_rows(len(rows)) if self._on_cpu else nullcontext():
                self.engine.start_rows(rows, latents, Conditions.collate(arrays))
            return
        # The first start, or a single rollout: a fresh engine, so frame positions restart at 0
        # and a reset with the same seed repeats the episode bit for bit.
        for i, row in enumerate(rows):
            self._pending[row] = (latents[i : i + 1], arrays[i])
        if len(self._pending) == self.n:
            order = sorted(self._pending)
            first = torch.cat([self._pending[r][0] for r in order])
            with torch.no_grad(), self._row_independent():
                self.engine.start(first, Conditions.collate([self._pending[r][1] for r in order]))
            self._pending.clear()

    def step(self, chunks: Sequence[Sequence[SceneFrame] | None]) -> list[list[Observation] | None]:
        """Advance every rollout whose chunk is given (``None``: idle, its output is discarded)."""
        if len(chunks) != self.n:
            raise ValueError(f"need one chunk (or None) per rollout: {self.n}, got {len(chunks)}")
        t0 = time.perf_counter()
        arrays = [
            None
            if chunk is None
            else self.wm.conditions.chunk_arrays(
                chunk, self.first[i], self.crops[i], self.crop_since[i], self.every_frame
            )
            for i, chunk in enumerate(chunks)
        ]
        self.seconds["conditions"] += time.perf_counter() - t0
        return self.step_arrays(arrays)

    def step_arrays(self, arrays: Sequence[Sequence[ConditionArrays] | None]) -> list[list[Observation] | None]:
        """:meth:`step` given each rollout's condition arrays, built by the caller
        (:meth:`ConditionBuilder.chunk_arrays`): one per causal chunk of the step, or ``None`` for an
        idle rollout. Returns each active rollout's observations of the step's last frame (of every
        frame with ``every_frame``)."""
        if len(arrays) != self.n:
            raise ValueError(f"need one list of condition arrays (or None) per rollout: {self.n}, got {len(arrays)}")
        if self.engine.batch_size != self.n:
            missing = [i for i in range(self.n) if i not in self._pending]
            raise RuntimeError(f"rollouts {missing} were never reset; reset every rollout before stepping")
        shapes = {tuple(a.num_frames for a in row) for row in arrays if row is not None}
        if len(shapes) > 1 or any(k != self.chunk_frames for shape in shapes for k in shape):
            raise ValueError(
                f"every rollout's step must be the same number of the model's {self.chunk_frames}-frame chunks, "
                f"got chunks of {sorted(shapes)} frames"
            )
        steps = len(next(iter(shapes), ()))
        outs: list[list[torch.Tensor]] = [[] for _ in range(self.n)]
        with torch.no_grad():
            for k in range(steps):
                batch = []
                for i, row in enumerate(arrays):
                    if row is not None:
                        self.last_arrays[i] = row[k]
                    # An idle row repeats its last controls: its output is thrown away.
                    arr = self.last_arrays[i]
                    batch.append(arr if arr.num_frames == self.chunk_frames else _repeat_frames(arr, self.chunk_frames))
                cond = Conditions.collate(batch)
                t0 = time.perf_counter()
                with self._row_independent():
                    latents = self.engine.step(cond)
                self._finish_device_work()
                self.seconds["student"] += time.perf_counter() - t0
                for i in range(self.n):
                    outs[i].append(latents[i : i + 1])
        t0 = time.perf_counter()
        active = [i for i, row in enumerate(arrays) if row is not None]
        results: list[list[Observation] | None] = [None] * self.n
        if active:  # one decoder call for every active rollout's frames
            lat = torch.cat([torch.cat(outs[i], dim=1) for i in active])
            labels = np.stack([np.concatenate([a.labels for a in arrays[i]]) for i in active])
            nearness = np.stack([np.concatenate([a.lidar_nearness for a in arrays[i]]) for i in active])
            if not self.every_frame:
                lat, labels, nearness = lat[:, -1:], labels[:, -1:], nearness[:, -1:]
            if self.wm.vae.draws_labels and (labels[..., CLASS_PLANE, 0, 0] == NO_LABEL).all(axis=-1).any():
                raise RuntimeError(
                    "a frame to decode has no label map: build each step's conditions with the rollouts' "
                    "every_frame (ConditionBuilder.chunk_arrays)"
                )
            style = np.stack([arrays[i][0].style for i in active])
            for i, obs in zip(active, self.wm.decode(lat, labels, style, nearness), strict=True):
                results[i] = obs
        self.seconds["decode"] += time.perf_counter() - t0
        return results


def _repeat_frames(arrays: ConditionArrays, frames: int) -> ConditionArrays:
    """The last frame of ``arrays`` repeated ``frames`` times (controls of an idle rollout)."""
    last = arrays.frames(arrays.num_frames - 1, arrays.num_frames)
    return replace(last, **{k: np.repeat(getattr(last, k), frames, axis=0) for k in ConditionArrays.TIME_FIELDS})
