"""The ``range_head`` stage: the VAE's range head trained alone on the student's own rollouts.

The run's label decoder (its ``rollout_decoder`` export, else ``decoder``) gains a
:class:`~world_model.model.range_head.RangeHead` (``layout.range_head``); every other weight stays
as it is, so the cameras and the DiTs are untouched. The run's student streams
:data:`~world_model.train.rollout_decoder_stage.ROLLOUT_CLIPS` training clips once as the env does
(the rollouts of the ``rollout_decoder`` stage, cached here too); each rolled-out frame's LiDAR view
is decoded once, and the head learns to finish it at the range map's resolution against the
recorded range map, from the range map the scene implies there (:func:`range_loss`, the objects'
cells weighing :data:`OBJECT_WEIGHT`). Its metrics compare the stretched view and the head on
the rolled-out frames: the median range error of the recording's object returns and the share
more than :data:`~world_model.eval.decisions.FAR_ERROR_M` off.

    RUN/range_head/rollouts.pt      the student's latents of the rolled-out clips (bf16), reused on resume
    RUN/range_head/model.*          the VAE with its trained head (EMA), the bundle's VAE
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from world_model.data.clips import Clip
from world_model.eval.decisions import FAR_ERROR_M, non_ground_returns
from world_model.model.config import ModelConfig, without_label_decoder
from world_model.model.range_head import finished_digest, range_loss
from world_model.model.vae import SensorVAE, ranges_to_image_values
from world_model.raster.maps import range_nearness_maps
from world_model.train.data import cached_nearness_maps, load_clips, nearness_cache_dir
from world_model.train.exports import EXPORT, load_vae, require_export, run_vae
from world_model.train.rollout_decoder_stage import rollout_clip_indices, student_rollouts
from world_model.train.run import StageRun
from world_model.train.trainer import Trainer
from world_model.train.vae_stage import check_decoder_config, export_vae

STAGE = "range_head"
DECODER_STAGES = ("rollout_decoder", "decoder")  # the label decoder the head finishes: the first exported
# The objects' cells in the loss, against one of the road's or the sky's: as the vae stage weighs
# the pixels inside objects' boxes (VaeConfig.object_loss_weight).
OBJECT_WEIGHT = 10.0
DECODE_BATCH = 64  # LiDAR views decoded per call while the examples are prepared
METRIC_FRAMES = 256  # rolled-out frames the export's metrics are measured on


def with_range_head(cfg: ModelConfig) -> ModelConfig:
    """``cfg`` whose VAE finishes the LiDAR with a range head."""
    return replace(cfg, layout=replace(cfg.layout, range_head=True))


@dataclass(frozen=True)
class RangeExamples:
    """The rolled-out frames the head learns from, N of them: each frame's decoded LiDAR view
    (N, 1, H, W) float32, the scene's nearness at the range map's resolution (N, beams, azimuth)
    uint8, the recorded range map in image values (N, 1, beams, azimuth) float16 and its object
    returns (N, 1, beams, azimuth) bool."""

    views: torch.Tensor
    nearness: torch.Tensor
    targets: torch.Tensor
    objects: torch.Tensor

    def batch(self, index: np.ndarray, device: torch.device) -> tuple[torch.Tensor, ...]:
        i = torch.from_numpy(index)
        return tuple(x[i].to(device) for x in (self.views, self.nearness, self.targets, self.objects))


def load_label_decoder(run: StageRun, cfg: ModelConfig) -> SensorVAE:
    """The run's label decoder (the first export of :data:`DECODER_STAGES`) as a VAE of ``cfg``,
    its range head as initialized."""
    for stage in DECODER_STAGES:
        path = run.run_dir / stage / EXPORT
        if path.with_suffix(".safetensors").exists():
            trained = load_vae(path)
            vae = SensorVAE(cfg)
            missing, unexpected = vae.load_state_dict(trained.state_dict(), strict=False)
            if unexpected or any(not k.startswith("range_head.") for k in missing):
                raise ValueError(f"{path.parent} holds a VAE of another config: train it again with the same --preset")
            return vae
    require_export(run.run_dir / DECODER_STAGES[-1] / EXPORT, DECODER_STAGES[-1])
    raise AssertionError("unreachable: require_export raises")


@torch.no_grad()
def range_examples(
    vae: SensorVAE, clips: list[Clip], rollouts: list[torch.Tensor], view_nearness: list[np.ndarray]
) -> RangeExamples:
    """Every frame of the rollouts (one per clip, frames as the clip's) as :class:`RangeExamples`."""
    cfg, lidar = vae.cfg, vae.cfg.sensors.lidar
    view = cfg.sensors.lidar_view
    views, nearness, targets, objects = [], [], [], []
    for clip, latents, near in zip(clips, rollouts, view_nearness, strict=True):
        n = len(latents)
        for s in range(0, n, DECODE_BATCH):
            z = latents[s : s + DECODE_BATCH, view].float()
            images = vae.decode(z, nearness=torch.from_numpy(np.asarray(near[s : s + DECODE_BATCH])), lidar=True)
            views.append(images.mean(dim=1, keepdim=True))
        nearness.append(torch.from_numpy(range_nearness_maps(clip.frames[:n], cfg)))
        recorded = np.asarray(clip.lidar[:n], np.float32)
        targets.append(ranges_to_image_values(torch.from_numpy(recorded), lidar)[:, None].half())
        objects.append(torch.from_numpy(np.stack([non_ground_returns(r, lidar) for r in recorded]))[:, None])
    return RangeExamples(*(torch.cat(x) for x in (views, nearness, targets, objects)))


@torch.no_grad()
def range_metrics(vae: SensorVAE, examples: RangeExamples, rng: np.random.Generator) -> dict[str, float]:
    """On up to :data:`METRIC_FRAMES` examples, the stretched view's and the head's errors on the
    recording's object returns: median metres, and the share more than ``FAR_ERROR_M`` off."""
    index = rng.choice(len(examples.views), size=min(METRIC_FRAMES, len(examples.views)), replace=False)
    views, nearness, targets, objects = examples.batch(np.sort(index), torch.device("cpu"))
    half_range = 0.5 * vae.cfg.sensors.lidar.max_range  # metres per image value
    stretched = torch.nn.functional.interpolate(views, size=targets.shape[-2:], mode="bilinear", align_corners=False)
    out = {}
    for name, values in (("stretched", stretched), ("head", vae.range_head(views, nearness))):
        err = ((values.clamp(-1, 1) - targets.float()).abs() * half_range)[objects]
        out[f"{name}_object_median_m"] = float(err.median()) if len(err) else float("nan")
        out[f"{name}_object_far_share"] = float((err > FAR_ERROR_M).float().mean()) if len(err) else float("nan")
    return out


def range_head_stage(run: StageRun) -> dict:
    """Train (or resume) ``RUN/range_head`` (module docstring)."""
    cfg, tcfg = with_range_head(run.cfg), run.tcfg
    check_decoder_config(cfg)
    plain, digest = run_vae(run.run_dir, without_label_decoder(cfg), STAGE)
    vae = load_label_decoder(run, cfg).eval().requires_grad_(False)
    clips = load_clips(run.data_dir, cfg)
    picked = [clips[i] for i in rollout_clip_indices(len(clips))]
    rollouts = student_rollouts(run, picked, plain, digest)
    near = cached_nearness_maps(picked, cfg, nearness_cache_dir(run.run_dir))
    examples = range_examples(vae, picked, rollouts, near)
    head = vae.range_head.to(run.place.device).requires_grad_(True)
    torch.manual_seed(tcfg.seed)
    trainer = run.trainer(head, STAGE, model_config=cfg.to_dict())

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        views, nearness, targets, objects = examples.batch(
            tr.rng.integers(len(examples.views), size=tcfg.batch_size), run.place.device
        )
        return range_loss(head(views, nearness), targets.float(), objects, OBJECT_WEIGHT), tcfg.batch_size

    summary = trainer.run(step, STAGE)
    if not run.place.is_main:
        return summary
    head.load_state_dict(trainer.ema.model_state(head))
    vae = vae.cpu().eval()
    metrics = range_metrics(vae, examples, np.random.default_rng(tcfg.seed))
    exported = export_vae(run, STAGE, vae, trainer.step, metrics, finishes=finished_digest(vae.state_dict()))
    return {**summary, "rollout_clips": len(rollouts), "metrics": exported}
