"""Rows of the report: what is evaluated. A row is any generator of sensors for a recorded clip at
equal controls, a callable ``Clip -> Generated``:

* reference rows: the Oracle (the recording itself), road-only (the recording without its
  objects) and first-frame (the recording frozen on its first frame) bound the scores;
* model rows: the causal student streaming each clip exactly as the env does (first frame from the
  reference-conditioned model, then one causal chunk at a time with the KV cache), the
  autoencoder's ceiling and the bidirectional teacher.

Which rows a bundle's report runs, under which streaming settings, is :mod:`~world_model.eval.report.lineup`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from world_model.data.clips import Clip
from world_model.model.conditions import Conditions
from world_model.model.dit import MultiViewDiT
from world_model.model.sampler import sample_latents, with_precipitation
from world_model.raster.crops import RecordedCrops
from world_model.rollout.batch import RolloutBatch
from world_model.rollout.conditions import RolloutConditions
from world_model.rollout.runtime import WorldModel
from world_model.sim import ProceduralSimulator
from world_model.streaming import StreamingConfig


@dataclass
class Generated:
    """A row's sensors for one clip: cameras uint8 (T, V, H, W, 3), optional LiDAR (T, beams, azimuth) m.

    ``pass_starts``: the frames (>= 1) that begin a new generation pass (the student's causal
    chunks, the teacher's windows), for the inter-chunk consistency scores; None for rows that
    are not generated in passes (the recording, the autoencoder)."""

    cameras: np.ndarray
    lidar: np.ndarray | None = None
    pass_starts: tuple[int, ...] | None = None


RowFn = Callable[[Clip], Generated]


def check_generated(gen: Generated, clip: Clip, row: str) -> None:
    """Refuse a row's output that does not match the clip it was asked for."""
    if not isinstance(gen, Generated):
        raise TypeError(f"row {row!r} must return a Generated, got {type(gen).__name__}")
    if gen.cameras.dtype != np.uint8 or gen.cameras.shape != clip.cameras.shape:
        raise ValueError(
            f"row {row!r} on clip {clip.name}: cameras must be uint8 {clip.cameras.shape}, "
            f"got {gen.cameras.dtype} {gen.cameras.shape}"
        )
    if gen.lidar is not None and gen.lidar.shape != clip.lidar.shape:
        raise ValueError(f"row {row!r} on clip {clip.name}: lidar must be {clip.lidar.shape}, got {gen.lidar.shape}")


def oracle_row(clip: Clip) -> Generated:
    """The ground truth itself: the upper bound of every judge score, Fréchet 0."""
    return Generated(cameras=np.asarray(clip.cameras), lidar=np.asarray(clip.lidar, dtype=np.float32))


def road_only_row(clip: Clip) -> Generated:
    """The recording re-rendered without its objects (the procedural simulator, same frames): the
    floor of the object scores (``object_psnr_db``, ``lidar_object_mae_m``, existence). A model
    whose object scores are no better than this does not keep the recording's objects."""
    sim = ProceduralSimulator()
    obs = [sim.render(replace(frame, objects=()), with_bev=False) for frame in clip.frames]
    return Generated(np.stack([o.cameras for o in obs]), np.stack([o.lidar for o in obs]).astype(np.float32))


def first_frame_row(clip: Clip) -> Generated:
    """The recording's first frame held for the whole clip: the floor of the motion scores (0) and
    what a rollout stuck on its start would score elsewhere. On a straight road its errors are low
    (the scene barely changes), so a model is only shown to follow the recording where it beats
    this row, not by low errors alone."""
    n = clip.num_frames
    return Generated(
        np.repeat(np.asarray(clip.cameras[:1]), n, axis=0), np.repeat(np.asarray(clip.lidar[:1], np.float32), n, axis=0)
    )


def world_model_row(
    wm: WorldModel,
    seed: int = 0,
    anchor_first_frame: bool = False,
    batch: int = 8,
    streaming: StreamingConfig | None = None,
) -> StudentRow:
    """A row generating each clip with ``wm``'s student (see :class:`StudentRow`).

    ``anchor_first_frame``: start from the clip's true first frame (all views, §6 task (a)) instead
    of sampling it from the controls. ``streaming``: how the student streams (None: as ``wm``
    does, its bundle's streaming.json; :meth:`StreamingConfig.override` makes a variant of it).
    """
    if streaming is not None:
        wm = replace(wm, student_cfg=replace(wm.student_cfg, streaming=streaming))
    return StudentRow(wm, seed, anchor_first_frame, batch)


class StudentRow:
    """Streams clips with the causal student exactly as the env does; ``generate_all`` runs up to
    ``batch`` clips as the rows of one batched rollout (idle once their clip ends), which is what
    makes a full evaluation set affordable on a CPU. Every clip's rollout draws its noise from its
    own generator seeded with ``seed``, so a clip's result does not depend on its batch-mates."""

    def __init__(self, wm: WorldModel, seed: int, anchor_first_frame: bool, batch: int) -> None:
        if batch < 1:
            raise ValueError(f"batch must be >= 1, got {batch}")
        self.wm, self.seed, self.anchor, self.batch = wm, seed, anchor_first_frame, batch

    def __call__(self, clip: Clip) -> Generated:
        return self.generate_all([clip])[0]

    def generate_all(self, clips: Sequence[Clip]) -> list[Generated]:
        for clip in clips:
            _check_resolution(self.wm, clip)
        out: list[Generated | None] = [None] * len(clips)
        order = sorted(range(len(clips)), key=lambda i: -clips[i].num_frames)  # batch similar lengths
        for g in range(0, len(order), self.batch):
            group = order[g : g + self.batch]
            for i, gen in zip(group, self._rollout([clips[i] for i in group]), strict=True):
                out[i] = gen
        return out  # type: ignore[return-value]

    def _rollout(self, clips: list[Clip]) -> list[Generated]:
        chunk = self.wm.cfg.clip.chunk_frames
        conditions = RolloutConditions(self.wm.conditions, len(clips), every_frame=True)
        rollout = RolloutBatch(self.wm, len(clips), every_frame=True)
        obs = []
        for r, clip in enumerate(clips):
            reference = {"cameras": np.asarray(clip.cameras[0])} if self.anchor else None
            first = clip.frames[0]
            arrays = conditions.restart(r, first, RecordedCrops(clip.crops, clip.crop_since))
            obs.append([rollout.start_row(r, first, self.seed, arrays, reference=reference)])
        rests = [list(clip.frames[1:]) for clip in clips]
        for k in range(0, max(len(rest) for rest in rests), chunk):
            arrays = []
            for r, rest in enumerate(rests):
                part = rest[k : k + chunk]
                part = part + [part[-1]] * (chunk - len(part)) if part else None  # pad the last chunk
                arrays.append(None if part is None else conditions.advance(r, part))
            for r, new in enumerate(rollout.step_arrays(arrays)):
                if new is not None:
                    obs[r] += new
        gens = []
        for clip, o in zip(clips, obs, strict=True):
            o = o[: clip.num_frames]
            cameras, lidar = np.stack([x.cameras for x in o]), np.stack([x.lidar for x in o])
            # Frame 0 comes from the reference model, then a causal chunk starts every `chunk` frames.
            starts = tuple(range(1, clip.num_frames, chunk))
            gens.append(Generated(cameras=cameras, lidar=lidar, pass_starts=starts))
        return gens


def autoencoder_row(wm: WorldModel, batch_frames: int = 16) -> RowFn:
    """The autoencoder's ceiling: each ground-truth frame encoded and decoded by ``wm``'s VAE, with
    the frame's rain or snow blended over its cameras as the env decodes them.

    No latent model (teacher or student) can score better than its autoencoder lets it, so this
    row tells which losses come from the VAE (objects a few pixels wide blurred away at 8x
    downsampling) and which from generation."""

    def row(clip: Clip) -> Generated:
        _check_resolution(wm, clip)
        cams, lids = [], []
        for s in range(0, clip.num_frames, batch_frames):
            part = slice(s, s + batch_frames)
            labels = wm.conditions.raster.labels(clip.frames[part])
            style = wm.conditions.style(clip.frames[0].prompt)
            nearness = wm.conditions.raster.nearness(clip.frames[part])
            ranges = wm.conditions.raster.range_nearness(clip.frames[part])
            c, lid = wm.vae.reconstruct_frames(clip.cameras[part], clip.lidar[part], labels, style, nearness, ranges)
            cams.append(with_precipitation(c, *wm.conditions.raster.precipitation(clip.frames[part])))
            lids.append(lid)
        return Generated(cameras=np.concatenate(cams), lidar=np.concatenate(lids))

    return row


def teacher_row(wm: WorldModel, teacher: MultiViewDiT, seed: int = 0, window: int | None = None) -> RowFn:
    """A row generating each clip with the bidirectional ``teacher`` (the teacher-vs-student ablation).

    The teacher has no streaming form: the clip is cut into windows of ``window`` frames (default
    its longest training length, ``clip.train_frames``), each sampled jointly from noise with the
    teacher's guided Euler sampler (``sampler.steps``), ego poses relative to the window's first
    frame as in training. Windows are independent, so motion is continuous inside a window only;
    ``wm`` supplies the VAE and the condition builder.
    """
    if teacher.cfg.shared_settings() != wm.cfg.shared_settings():  # depth, window may differ
        raise ValueError("the teacher and the bundle were trained with different configs")
    w = window or max(wm.cfg.clip.train_frames)

    def row(clip: Clip) -> Generated:
        _check_resolution(wm, clip)
        frames, obs = clip.frames, []
        gen = torch.Generator().manual_seed(seed)
        for start in range(0, len(frames), w):
            part = frames[start : start + w]
            cond = Conditions.collate([wm.conditions.arrays(part, part[0], clip.crops, clip.crop_since)])
            obs += wm.decode(sample_latents(teacher, cond, gen), **cond.decoder_inputs())[0]
        cameras, lidar = np.stack([o.cameras for o in obs]), np.stack([o.lidar for o in obs])
        return Generated(cameras=cameras, lidar=lidar, pass_starts=tuple(range(w, len(frames), w)))

    return row


def _check_resolution(wm: WorldModel, clip: Clip) -> None:
    h, w = wm.cfg.sensors.height, wm.cfg.sensors.width
    if clip.cameras.shape[2:4] != (h, w):
        raise ValueError(
            f"clip {clip.name} was recorded at {clip.cameras.shape[2:4]}, the model generates {(h, w)}: "
            "record the evaluation set at the model's resolution"
        )
