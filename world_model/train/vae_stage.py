"""``--stage vae``: the camera/LiDAR autoencoder, trained on random sensor frames; and
``--stage decoder``: its decoder again, drawing each camera's label map (``layout.decoder``).

The decoder stage keeps the ``vae`` stage's encoder and latent statistics frozen, so the latents
every DiT is trained on stay what they were and the stage may run at any point after ``vae``. The
decoder starts as the plain one (its label modulations zero-initialized) and learns, on the run's
cached latents, to draw the road, the markings and the objects where the label maps put them.
The latents it decodes are jittered with Gaussian noise: the student's are not the encoder's.
The decoder reads each clip's prompt too (the scene's style), and its latents also drift by a
smooth random field: the student's colours wander (a rainy day's sky turning dusk-orange), so the
sky, road and ground must take their look from the prompt. It decodes half of its LiDAR-view
samples from the latent of a nearby frame (:func:`latent_frames`): the returns must stand where
the scene's nearness map puts the objects, not where a lagging latent has them.

Layout: ``RUN/vae/`` and ``RUN/decoder/`` each hold checkpoints/, model.safetensors + model.json
(EMA weights, latent statistics, reconstruction metrics) and metrics.json.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from world_model.data.clips import Clip, write_json_atomic
from world_model.model.conditions import style_of_prompt
from world_model.model.config import ModelConfig, without_label_decoder
from world_model.model.text import make_text_encoder
from world_model.model.vae import (
    LABEL_DECODER_WEIGHTS,
    SensorVAE,
    images_to_cameras,
    images_to_lidar,
    kl_loss,
    weighted_l1,
)
from world_model.raster.classes import CLASS_PLANE, VEHICLE, blank_maps
from world_model.raster.maps import lidar_nearness_maps
from world_model.scene import SceneFrame
from world_model.sim.labels import LabelRasterizer
from world_model.train.checkpoint import export_weights
from world_model.train.data import (
    FrameSampler,
    cached_label_maps,
    cached_nearness_maps,
    label_cache_dir,
    load_clips,
    nearness_cache_dir,
)
from world_model.train.exports import EXPORT, run_latents, run_vae
from world_model.train.run import StageRun
from world_model.train.trainer import Trainer

EVAL_FRAMES = 32  # frames used for the VAE's reconstruction metrics
STATS_FRAMES = 64  # frames used to fit the latent normalization
# Largest standard deviation of the noise added to a decoder-stage latent (normalized units, drawn
# uniformly per sample from [0, this]): the student's latents are near the encoder's, not on them.
DECODER_LATENT_NOISE = 0.3
# Largest amplitude of the smooth drift added to a label decoder's latents (normalized units, a
# per-sample amplitude drawn uniformly from [0, this] times a bilinear field over a coarse grid of
# Gaussian values, DRIFT_GRID cells): regional, like the student's colour drift.
DECODER_STYLE_DRIFT = 0.8
DRIFT_GRID = (2, 4)
# A label decoder decodes this share of its LiDAR-view samples from
# the latent of another frame of the clip, up to LIDAR_LATENT_LAG frames away: the student's LiDAR
# objects lag the scene (they hardly follow the ego's braking), and the decoder must learn to stand
# the returns where the nearness map says rather than where the latent has them.
LIDAR_LAG_SHARE = 0.5
LIDAR_LATENT_LAG = 20


@torch.no_grad()
def vae_metrics(
    vae: SensorVAE,
    sampler: FrameSampler,
    labels: LabelRasterizer | None = None,
    styles: Sequence[np.ndarray] | None = None,
) -> dict[str, float]:
    """Camera PSNR (dB, uint8 images) and LiDAR range MAE (m, on true returns) + no-return accuracy.
    ``labels`` renders the label maps and ``styles`` holds each clip's scene style, for a decoder
    that draws the scene."""
    cfg = vae.cfg
    spec = cfg.sensors.lidar
    device = next(vae.parameters()).device
    se, count, abs_err, n_ret, nr_ok, n_all = 0.0, 0, 0.0, 0, 0, 0
    for ci, f in sampler.eval_frames(EVAL_FRAMES):
        clip = sampler.clips[ci]
        cams = np.asarray(clip.cameras[f])
        x = torch.stack([sampler.image(ci, f, v) for v in range(cfg.sensors.num_views)]).to(device)
        views = range(cfg.sensors.num_views)
        ids = view_labels(labels, clip.frames[f], cfg, views).to(device) if labels else None
        near = view_nearness(clip.frames[f], cfg, views).to(device) if vae.draws_labels else None
        style = None if styles is None else torch.from_numpy(styles[ci]).to(device).expand(len(x), -1)
        lidar = torch.arange(len(x)) == cfg.sensors.lidar_view
        rec = vae.decode(vae.encode(x), ids, style, near, lidar).float().cpu()
        se += float(((images_to_cameras(rec[:-1]).astype(np.float64) - cams) ** 2).sum())
        count += cams.size
        truth = np.asarray(clip.lidar[f], dtype=np.float32)
        pred = images_to_lidar(rec[-1], spec, cfg.vae.lidar_no_return_fraction)
        ret = truth > spec.no_return
        abs_err += float(np.abs(pred - truth)[ret].sum())
        n_ret += int(ret.sum())
        nr_ok += int(((pred > spec.no_return) == ret).sum())
        n_all += truth.size
    mse = se / max(count, 1)
    return {
        "camera_psnr_db": 10 * math.log10(255.0**2 / max(mse, 1e-10)),
        "lidar_range_mae_m": abs_err / max(n_ret, 1),
        "lidar_return_accuracy": nr_ok / max(n_all, 1),
    }


def view_labels(raster: LabelRasterizer, frame: SceneFrame, cfg: ModelConfig, views: Iterable[int]) -> torch.Tensor:
    """(N, 3, H, W) uint8 label maps (class ids, paint, surface) of ``views`` of ``frame``; the LiDAR view
    gets a map that draws nothing (:func:`~world_model.raster.classes.blank_maps`), as it does when decoding frames."""
    s = cfg.sensors
    maps = torch.from_numpy(raster.maps(frame, frame.rig, s.height, s.width))
    blank = torch.from_numpy(blank_maps((), s.height, s.width))
    return torch.stack([maps[v] if v < s.num_cameras else blank for v in views])


def view_nearness(frame: SceneFrame, cfg: ModelConfig, views: Iterable[int]) -> torch.Tensor:
    """(N, H, W) uint8 nearness maps of ``views`` of ``frame``: the LiDAR view's
    (:func:`~world_model.raster.maps.lidar_nearness_maps`), zeros for a camera, as when decoding frames."""
    s = cfg.sensors
    lidar = torch.from_numpy(lidar_nearness_maps([frame], cfg)[0])
    return torch.stack([lidar if v == s.lidar_view else torch.zeros_like(lidar) for v in views])


def picked_nearness(nearness: Sequence[np.ndarray], clip: int, frame: int, view: int, cfg: ModelConfig) -> np.ndarray:
    """(H, W) uint8 nearness map of a view of a frame from each clip's LiDAR nearness maps; zeros
    for a camera, as in :func:`view_nearness`."""
    if view == cfg.sensors.lidar_view:
        return nearness[clip][frame]
    return np.zeros((cfg.sensors.height, cfg.sensors.width), np.uint8)


def picked_labels(labels: Sequence[np.ndarray], clip: int, frame: int, view: int, cfg: ModelConfig) -> np.ndarray:
    """(3, H, W) uint8 label map of a view of a frame from each clip's camera label maps; the LiDAR
    view gets a map that draws nothing, as in :func:`view_labels`."""
    if view < cfg.sensors.num_cameras:
        return labels[clip][frame, view]
    return blank_maps((), cfg.sensors.height, cfg.sensors.width)


def vae_stage(run: StageRun) -> dict:
    """Train (or resume) ``RUN/vae`` (module docstring)."""
    cfg, tcfg = without_label_decoder(run.cfg), run.tcfg
    sampler = FrameSampler(load_clips(run.data_dir, cfg), cfg)
    torch.manual_seed(tcfg.seed)
    vae = SensorVAE(cfg)
    trainer = run.trainer(vae, "vae")

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        batch = sampler.sample(tr.rng, tcfg.batch_size)
        images, is_lidar, weights = tr.shard(batch.images), tr.shard(batch.is_lidar), tr.shard(batch.weights)
        mean, logvar = vae.posterior(images)
        eps = tr.shard(tr.randn(tcfg.batch_size, *mean.shape[1:]))
        z = mean + (0.5 * logvar).exp() * eps
        err = weighted_l1(vae.decode_raw(z), images, weights)
        weight = torch.where(is_lidar, cfg.vae.lidar_loss_weight, 1.0)
        return (err * weight).mean() + cfg.vae.kl_weight * kl_loss(mean, logvar), len(images)

    summary = trainer.run(step, "vae")
    if not run.place.is_main:
        return summary
    final = SensorVAE(cfg)
    final.load_state_dict(trainer.ema.model_state(vae))
    stats_rng = np.random.default_rng(tcfg.seed)
    final.set_latent_stats(sampler.sample(stats_rng, STATS_FRAMES).images)
    final.eval()
    return {**summary, "metrics": export_vae(run, "vae", final, trainer.step, vae_metrics(final, sampler))}


def check_decoder_config(cfg: ModelConfig) -> None:
    """The decoder stage trains only a decoder that draws label maps (``layout.decoder``)."""
    if not cfg.layout.decoder:
        raise ValueError("--stage decoder trains the decoder that draws the layout's label maps: train with --layout")


def decoder_stage(run: StageRun) -> dict:
    """Train (or resume) ``RUN/decoder``: the ``vae`` stage's autoencoder with a decoder that draws
    each camera's label map (module docstring)."""
    cfg, tcfg = run.cfg, run.tcfg
    check_decoder_config(cfg)
    plain, digest = run_vae(run.run_dir, without_label_decoder(cfg), "decoder")
    clips = load_clips(run.data_dir, cfg)
    sampler = FrameSampler(clips, cfg)
    latents = run_latents(clips, plain, digest, run.run_dir, run.place.device)
    labels, nearness = decoder_maps(run, clips)
    torch.manual_seed(tcfg.seed)
    vae = SensorVAE(cfg)
    missing, unexpected = vae.load_state_dict(plain.state_dict(), strict=False)
    if unexpected or any(not k.startswith(LABEL_DECODER_WEIGHTS) for k in missing):
        raise ValueError(f"the VAE in {run.run_dir / 'vae'} does not fit this config: {missing + unexpected}")
    vae.encoder.requires_grad_(False)
    trainer = run.trainer(vae, "decoder")
    raster = LabelRasterizer()
    styles = clip_styles(vae, clips)
    lengths = [len(x) for x in latents]
    targets = DecoderTargets(sampler, labels, nearness, styles)

    def step(tr: Trainer) -> tuple[torch.Tensor, int]:
        picks = sampler.pick(tr.rng, tcfg.batch_size)
        frames = decoded_frames(tr.rng, vae, picks, lengths)
        z = torch.stack([latents[c][g, v] for (c, _, v), g in zip(picks, frames, strict=True)]).float()
        z = jittered_latents(tr, z, styles is not None)
        return decoder_loss(tr, vae, targets, picks, z)

    summary = trainer.run(step, "decoder")
    if not run.place.is_main:
        return summary
    return {**summary, "metrics": export_decoder(run, "decoder", trainer, vae, plain, sampler, raster, styles)}


def decoder_maps(run: StageRun, clips: list[Clip]) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
    """Each clip's camera label maps (:func:`cached_label_maps`) and, for a decoder that draws them,
    its LiDAR nearness maps (:func:`cached_nearness_maps`; else None), from the run's caches."""
    labels = cached_label_maps(clips, run.cfg, label_cache_dir(run.run_dir))
    return labels, cached_nearness_maps(clips, run.cfg, nearness_cache_dir(run.run_dir))


def clip_styles(vae: SensorVAE, clips: Sequence[Clip]) -> list[np.ndarray] | None:
    """Each clip's scene style (its prompt's, ``ConditionArrays.style``) for a decoder that draws
    the scene; None for one that does not."""
    if not vae.draws_labels:
        return None
    text = make_text_encoder(vae.cfg.text)
    return [style_of_prompt(c.frames[0].prompt, vae.cfg, text) for c in clips]


def jittered_latents(tr: Trainer, z: torch.Tensor, drift: bool) -> torch.Tensor:
    """The decoder stage's latents (N, C, h, w): Gaussian jitter of a per-sample standard deviation
    drawn from [0, :data:`DECODER_LATENT_NOISE`], plus :func:`style_drift` when ``drift``; on the
    training device, where the trainer draws its noise."""
    noise = tr.randn(*z.shape)
    sigma = torch.from_numpy(tr.rng.uniform(0.0, DECODER_LATENT_NOISE, size=(len(z), 1, 1, 1))).float()
    z = z.to(noise.device) + sigma.to(noise.device) * noise
    return z + style_drift(tr, len(z), z.shape[1:]) if drift else z


@dataclass(frozen=True)
class DecoderTargets:
    """What a label decoder learns to draw, per clip of the run: its frames (``sampler``), camera
    ``labels`` (:func:`cached_label_maps`), LiDAR ``nearness`` maps (:func:`cached_nearness_maps`)
    and prompt ``styles`` (:func:`clip_styles`; None for a decoder without a style)."""

    sampler: FrameSampler
    labels: Sequence[np.ndarray]
    nearness: Sequence[np.ndarray] | None
    styles: Sequence[np.ndarray] | None


def decoder_loss(
    tr: Trainer,
    vae: SensorVAE,
    targets: DecoderTargets,
    picks: Sequence[tuple[int, int, int]],
    latents: torch.Tensor,
    cameras_about_vehicles: CameraTuning | None = None,
) -> tuple[torch.Tensor, int]:
    """The label decoder's loss on (clip, frame, view) ``picks`` of ``targets`` decoded from
    ``latents`` (N, C, h, w), and the batch size. With ``cameras_about_vehicles`` the cameras' own
    decoder learns the recording about the vehicles only (:class:`CameraTuning`)."""
    cfg, styles, labels, nearness = vae.cfg, targets.styles, targets.labels, targets.nearness
    batch = targets.sampler.batch(picks)
    images, is_lidar, weights = tr.shard(batch.images), tr.shard(batch.is_lidar), tr.shard(batch.weights)
    style = None if styles is None else tr.shard(torch.from_numpy(np.stack([styles[c] for c, _, _ in picks])))
    ids = tr.shard(torch.from_numpy(np.stack([picked_labels(labels, c, f, v, cfg) for c, f, v in picks])))
    near = None
    if nearness is not None:
        near = tr.shard(torch.from_numpy(np.stack([picked_nearness(nearness, c, f, v, cfg) for c, f, v in picks])))
    place = tr.place
    # This rank's rows from the host's batch: which decoder draws a row is read on the CPU, never
    # copied back from the training device.
    own_lidar = batch.is_lidar[place.local_rows(len(picks))] if place.distributed else batch.is_lidar
    z = tr.shard(latents)
    drawn = vae.decode(z, ids, style, near, own_lidar)
    if cameras_about_vehicles is not None:
        with torch.no_grad():
            shared = vae.decode(z, ids, style, near, True)  # every latent drawn by the shared decoder
        images, weights = cameras_about_vehicles.targets(images, shared.to(images.dtype), weights, ids)
    err = weighted_l1(drawn, images, weights)
    return (err * torch.where(is_lidar, cfg.vae.lidar_loss_weight, 1.0)).mean(), len(images)


@dataclass(frozen=True)
class CameraTuning:
    """What the cameras' own decoder learns: the recording where the label map has a vehicle, within
    ``margin`` pixels of one, and about its bottom edge (the lowest vehicle pixel of a column's
    run and the road under it, ``edge_rows`` rows either way), those edge pixels weighing
    ``edge_weight`` times any other; elsewhere the shared decoder's own drawing of the same
    latents, so that the road and its markings stay as the lane finders read them. Where the car
    ahead stands on the road is a few rows of a few columns, and a camera policy reads its range
    from them."""

    edge_weight: float = 10.0
    edge_rows: int = 2
    margin: int = 1

    def targets(
        self, images: torch.Tensor, shared: torch.Tensor, weights: torch.Tensor, labels: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Targets (N, 3, H, W) and per-pixel weights (N, 1, H, W) from the recorded ``images``,
        the ``shared`` decoder's drawing, the batch's ``weights`` and label maps ``labels`` (N, 3, H, W)."""
        vehicle = (labels[:, CLASS_PLANE : CLASS_PLANE + 1] == VEHICLE).float()
        edge = bottom_edge_band(vehicle, self.edge_rows)
        zone = F.max_pool2d(torch.maximum(vehicle, edge), 2 * self.margin + 1, stride=1, padding=self.margin) > 0
        return torch.where(zone, images, shared), weights * (1.0 + (self.edge_weight - 1.0) * edge)


def bottom_edge_band(mask: torch.Tensor, rows: int) -> torch.Tensor:
    """(N, 1, H, W) float 0/1: the pixels within ``rows`` rows of the bottom edge of ``mask``'s
    runs (N, 1, H, W, 0/1), the edge being the first pixel under a run."""
    above = F.pad(mask[:, :, :-1], (0, 0, 1, 0))  # the mask one row up
    under = (1.0 - mask) * above
    return F.max_pool2d(under, kernel_size=(2 * rows + 1, 1), stride=1, padding=(rows, 0))


def export_decoder(
    run: StageRun,
    stage: str,
    trainer: Trainer,
    vae: SensorVAE,
    plain: SensorVAE,
    sampler: FrameSampler,
    raster: LabelRasterizer,
    styles: Sequence[np.ndarray] | None,
) -> dict[str, float]:
    """Export a decoder stage's EMA weights with ``plain``'s encoder, bit for bit (the EMA rounds a
    frozen weight); its metrics."""
    final = SensorVAE(vae.cfg)
    final.load_state_dict(trainer.ema.model_state(vae))
    final.encoder.load_state_dict(plain.encoder.state_dict())
    final.eval()
    return export_vae(run, stage, final, trainer.step, vae_metrics(final, sampler, raster, styles))


def latent_frames(
    rng: np.random.Generator, picks: Sequence[tuple[int, int, int]], lengths: Sequence[int], cfg: ModelConfig
) -> list[int]:
    """The frame whose latent each (clip, frame, view) pick is decoded from, for a label decoder:
    the pick's own frame, except for :data:`LIDAR_LAG_SHARE` of the
    LiDAR view's, a frame up to :data:`LIDAR_LATENT_LAG` away within the clip (``lengths``: frames
    per clip). The draws do not depend on the picks' views, so a batch's random stream stays put."""
    lagged = rng.random(len(picks)) < LIDAR_LAG_SHARE
    shift = rng.integers(-LIDAR_LATENT_LAG, LIDAR_LATENT_LAG + 1, size=len(picks))
    lidar = cfg.sensors.lidar_view
    return [
        min(max(f + int(d), 0), lengths[c] - 1) if v == lidar and lag else f
        for (c, f, v), lag, d in zip(picks, lagged, shift, strict=True)
    ]


def decoded_frames(
    rng: np.random.Generator, vae: SensorVAE, picks: Sequence[tuple[int, int, int]], lengths: Sequence[int]
) -> list[int]:
    """The frame whose latent each (clip, frame, view) pick is decoded from: :func:`latent_frames`
    for a decoder that draws the scene, else the pick's own (no random draw)."""
    return latent_frames(rng, picks, lengths, vae.cfg) if vae.draws_labels else [f for _, f, _ in picks]


def style_drift(tr: Trainer, n: int, shape: torch.Size) -> torch.Tensor:
    """(n, C, h, w) smooth random latent drift (:data:`DECODER_STYLE_DRIFT`), drawn from the trainer's
    random streams."""
    amplitude = torch.from_numpy(tr.rng.uniform(0.0, DECODER_STYLE_DRIFT, size=(n, 1, 1, 1))).float()
    coarse = tr.randn(n, shape[0], *DRIFT_GRID)
    drift = F.interpolate(coarse, size=tuple(shape[1:]), mode="bilinear", align_corners=True)
    return amplitude.to(coarse.device) * drift


def export_vae(
    run: StageRun, stage: str, vae: SensorVAE, step: int, metrics: dict[str, float], **meta: object
) -> dict[str, float]:
    """Write ``RUN/<stage>/model`` (weights, config, metrics, ``meta``) and its metrics.json; the metrics."""
    meta = {"stage": stage, "step": step, "model_config": vae.cfg.to_dict(), "metrics": metrics, **meta}
    export_weights(run.stage_dir / EXPORT, vae.state_dict(), meta)
    write_json_atomic(run.stage_dir / "metrics.json", {"step": step, **metrics})
    return metrics
