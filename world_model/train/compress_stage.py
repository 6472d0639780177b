"""``compress`` stage: a smaller or faster causal student distilled from a trained one.

The env's speed is the student's: its depth and its rolling window (docs/MODEL_CARD.md, "Speed").
Distilling a shallower student from the bidirectional teacher again (tf -> ode -> dmd -> long) left
its LiDAR drifting or its scenes collapsing onto a mean (the model card's shallow-student tables).
This stage instead imitates a student that already behaves: the *source* (default ``RUN/long``;
``--base`` a checkpoint bundle such as the shipped one, or another exported student).

On-policy output matching (DAgger-style, as in the ODE initialization of §4.2 but with the source
student's x0-prediction as the target). Both students roll out together from the same real first
frames under the same controls; the rollout is the *compressed* student's own: at each of its
denoising steps it sees its own x_t, and the source predicts x0 from the same x_t after the same
history. The loss is the mean squared error between the two x0-predictions at every denoising step
of every trained chunk; the compressed student's clean chunk is then committed to both caches (the
source's through :meth:`StreamingEngine.commit`, its teacher-forcing entry), so the source always
judges the history the compressed student actually generated, the way the env will run it. The
target is a deterministic function of the same input noise, so regressing on it keeps the source's
detail instead of averaging over its samples. With ``StudentConfig.compress_object_weight`` w > 0
the mean is weighted 1 + w on the latent cells inside any object's projected 3-D box in the
frames' recorded layout (the controls the students are conditioned on), since vehicles cover a few
percent of the cells and a plain mean lets the compressed student drop them.

Rollouts continue across steps as in ``long`` (``StudentConfig.long_frames`` frames, then a fresh
start from data; ``long_clip_chunks`` trained chunks per step, ``long_skip_chunks`` untrained
ones between), so the late frames of a minute-long rollout are trained too. A resumed run starts a
fresh rollout. The compressed student starts from evenly spaced source blocks
(:func:`student_from_teacher`) and keeps its own :class:`StudentConfig` (e.g. another window).

A bundle source brings its own latent space: its VAE (and reference model, if any) is written to
``RUN/vae`` and ``RUN/reference`` when those are missing, so the data is encoded in the source's
latents and ``m4world export`` finds every component; an existing ``RUN/vae`` must be the bundle's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from world_model.model.conditions import Conditions
from world_model.model.dit import MultiViewDiT
from world_model.student.config import StudentConfig
from world_model.student.engine import StreamingEngine, X0Fn
from world_model.student.init import student_from_teacher
from world_model.student.losses import ode_regression_loss
from world_model.train.checkpoint import export_weights
from world_model.train.data import LatentWindows
from world_model.train.stages import EXPORT, load_vae
from world_model.train.trainer import Trainer

if TYPE_CHECKING:
    from world_model.runtime import WorldModel
    from world_model.train.student_stages import StageRun

SOURCE_STAGE = "long"  # the default source: the run's own finished student


@dataclass
class CompressSource:
    """The trained student imitated, with its streaming settings and where it came from."""

    model: MultiViewDiT
    scfg: StudentConfig
    file: Path


def _adopt_bundle_parts(wm: WorldModel, run_dir: Path) -> None:
    """Write the loaded bundle's VAE (and reference model) as ``RUN/vae`` (``RUN/reference``) when
    missing; refuse a run whose VAE is another one (its latents would not be the source's)."""
    bundle = wm.path
    vae_path = run_dir / "vae" / EXPORT
    if vae_path.with_suffix(".safetensors").exists():
        mine = load_vae(vae_path).state_dict()
        theirs = wm.vae.state_dict()
        if mine.keys() != theirs.keys() or any(not torch.equal(mine[k], theirs[k]) for k in mine):
            raise ValueError(
                f"{vae_path}.safetensors is not the VAE of {bundle}: the source student works in its "
                "bundle's latents; compress into a new run directory"
            )
    else:
        meta = {"stage": "vae", "model_config": wm.vae.cfg.to_dict(), "source": str(bundle)}
        export_weights(vae_path, wm.vae.state_dict(), meta)
    ref_path = run_dir / "reference" / EXPORT
    if wm.reference is not None and not ref_path.with_suffix(".safetensors").exists():
        meta = {"stage": "reference", "model_config": wm.reference.cfg.to_dict(), "source": str(bundle)}
        export_weights(ref_path, wm.reference.state_dict(), meta)  # float32: loaded so


def load_source(base: str | Path | None, run_dir: Path) -> CompressSource:
    """The source student: ``base`` None (``RUN/long/model``), an exported student (e.g.
    ``RUN/dmd/model``), or a checkpoint bundle (its student; its VAE and reference model are
    adopted into the run, see the module docstring). Float32 weights, frozen."""
    from world_model.train.lora_stage import bundle_model
    from world_model.train.student_stages import load_student

    in_bundle = bundle_model(base)
    if in_bundle is not None:
        bundle, component = in_bundle
        if component != "student":
            raise ValueError(f"--stage compress distills a student; {base} is the bundle's {component} model")
        from world_model.runtime import load_world_model

        wm = load_world_model(bundle, dtype="float32")
        _adopt_bundle_parts(wm, run_dir)
        model, scfg, file = wm.student, wm.student_cfg, bundle / "student.safetensors"
    else:
        path = Path(base).with_suffix("") if base else run_dir / SOURCE_STAGE / EXPORT
        file = path.with_suffix(".safetensors")
        if not file.exists():
            raise FileNotFoundError(
                f"--stage compress distills {file}, which does not exist; run --stage {SOURCE_STAGE} first, "
                "or pass --base (an exported student or a checkpoint bundle such as the shipped default)"
            )
        model, scfg = load_student(path)
    return CompressSource(model.float().eval().requires_grad_(False), scfg, file)


def matched(x0_fn: X0Fn, target_fn: X0Fn, losses: list[torch.Tensor], weights: torch.Tensor | None = None) -> X0Fn:
    """``x0_fn`` as the sampler sees it (its prediction, detached: the rollout stays the student's
    own), appending at each call the regression loss onto ``target_fn``'s prediction at the same
    (x_t, t) to ``losses`` (weighted by ``weights`` (B, T, V, 1, h, w) when given)."""

    def fn(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            target = target_fn(x, t)
        with torch.enable_grad():
            pred = x0_fn(x, t)
        losses.append(ode_regression_loss(pred, target, weights))
        return pred.detach()

    return fn


def object_weights(windows: LatentWindows, clips: list[int], start: int, frames: int, weight: float) -> torch.Tensor:
    """(B, frames, V, 1, h, w) loss weights of rollout frames [start, start + frames) per row (the
    clips played back and forth as their conditions are): 1 + ``weight`` on the latent cells inside
    any object's exact projected box, 1 elsewhere."""
    from world_model.model.reference import ReferenceConfig, category_region
    from world_model.train.student_stages import rollout_frame_indices

    rcfg = ReferenceConfig(margin_px=0)
    rows = []
    for ci in clips:
        clip = windows.clips[ci]
        scene = [clip.frames[i] for i in rollout_frame_indices(clip.num_frames, start, frames)]
        rows.append(category_region(scene, None, windows.cfg, rcfg))
    region = torch.from_numpy(np.stack(rows))[:, :, :, None]
    return torch.where(region, 1.0 + weight, 1.0)


def compress_stage(run: StageRun, source: CompressSource) -> dict:
    """Train ``RUN/compress`` (see the module docstring) on rollouts started from ``run.windows``' clips."""
    from world_model.train.student_stages import _export, _long_conditions, rollout_starts

    windows, stage_dir, cfg, scfg, tcfg = run.windows, run.stage_dir, run.cfg, run.scfg, run.tcfg

    scfg_src = source.scfg
    if (scfg_src.prefix_frames, scfg_src.denoising_steps, scfg_src.timestep_shift) != (
        scfg.prefix_frames,
        scfg.denoising_steps,
        scfg.timestep_shift,
    ):
        raise ValueError(
            "the compressed student must keep the source's prefix frames and denoising schedule "
            f"(source: {scfg_src.prefix_frames} prefix frames, steps {scfg_src.denoising_steps}, "
            f"shift {scfg_src.timestep_shift})"
        )
    if source.model.cfg.shared_settings() != cfg.shared_settings():
        raise ValueError(
            f"the source student {source.file} was trained with preset {source.model.cfg.name!r}'s sensors, "
            f"VAE or controls, not {cfg.name!r}'s: pass the same --preset"
        )
    student = student_from_teacher(source.model, cfg.for_student()).train().requires_grad_(True)
    trainer = run.trainer(student, "compress", source=str(source.file))
    c, p = cfg.clip.chunk_frames, scfg.prefix_frames
    clip_frames = scfg.long_clip_chunks * c
    mine = StreamingEngine(student, scfg, trainer.gen)
    theirs = StreamingEngine(source.model, scfg_src)  # draws no noise: it only predicts and commits
    state: dict = {"clips": None}

    def start(tr: Trainer) -> None:
        clips, first, cond = rollout_starts(windows, tr.rng, tcfg.batch_size, p)
        mine.start(first, cond)
        theirs.start(first, cond)
        state["clips"] = clips

    def advance(controls: Conditions, losses: list[torch.Tensor] | None) -> None:
        """One chunk of the compressed student's rollout, committed to both caches; trained when
        ``losses`` collects the per-step regression losses."""
        if losses is None:
            with torch.no_grad():
                x0 = mine.step(controls)
        else:
            target_fn = theirs.chunk_x0_fn(controls)
            weights = None
            if scfg.compress_object_weight:
                weights = object_weights(windows, state["clips"], mine.position, c, scfg.compress_object_weight)
            x0 = mine.step(controls, grad=True, through=lambda fn: matched(fn, target_fn, losses, weights))
        theirs.commit(x0.detach(), controls)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        skip = scfg.long_skip_chunks * c
        if state["clips"] is None or mine.position + skip + clip_frames > scfg.long_frames:
            start(tr)
        else:
            for _ in range(scfg.long_skip_chunks):
                advance(_long_conditions(windows, state["clips"], mine.position, c, 0), None)
        controls = _long_conditions(windows, state["clips"], mine.position, clip_frames, 0)
        losses: list[torch.Tensor] = []
        for k in range(scfg.long_clip_chunks):
            advance(controls.frames(k * c, (k + 1) * c), losses)
        return torch.stack(losses).mean(), tcfg.batch_size * clip_frames

    summary = trainer.run(step, "compress")
    _export(stage_dir, trainer, trainer.ema.model_state(student), student.cfg, scfg, "compress")
    return {**summary, "rollout_frames": mine.position, "source": str(source.file)}
