"""Model configuration: one dataclass per concern, every default visible, three presets.

Token counts and tensor shapes are *derived* here (properties), never hard-coded elsewhere:

* views        = cameras + 1 (the LiDAR range map is the last view, paper §3.2)
* latent grid  = image size / VAE downsampling (``2 ** len(channel_mults)``)
* tokens/frame = latent grid / DiT patch size
* map tokens   = BEV raster / map patch size

Presets (:func:`get_preset`): ``tiny`` (tests, seconds), ``default`` (the CPU preset that is
trained and shipped), ``gpu`` (near the paper's dimensions; not trainable on this machine).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field, replace
from typing import Any

from world_model.model.layout import LAYOUT_CHANNELS
from world_model.raster.classes import LABEL_CLASSES
from world_model.sensors import BevSpec, CameraRig, LidarSpec, default_rig


@dataclass(frozen=True)
class SensorConfig:
    """Which sensors the model generates, and at which resolution."""

    num_cameras: int = 6
    height: int = 64
    width: int = 112
    lidar: LidarSpec = field(default_factory=LidarSpec)
    bev: BevSpec = field(default_factory=BevSpec)

    @property
    def num_views(self) -> int:
        """Cameras plus the LiDAR view (always last)."""
        return self.num_cameras + 1

    @property
    def lidar_view(self) -> int:
        return self.num_cameras

    def rig(self) -> CameraRig:
        """The default rig at this resolution (the first ``num_cameras`` cameras of it)."""
        rig = default_rig(width=self.width, height=self.height)
        return CameraRig(cameras=rig.cameras[: self.num_cameras])


@dataclass(frozen=True)
class VaeConfig:
    """Per-frame spatial autoencoder shared by cameras and LiDAR range maps (§3.2)."""

    image_channels: int = 3  # RGB; a range map is repeated on the 3 channels
    latent_channels: int = 8
    channel_mults: tuple[int, ...] = (1, 2, 4)  # one stride-2 level each: 8x downsampling
    base_channels: int = 16
    decoder_base_channels: int = 12  # decoding 8 envs x 7 views x 2 frames per env step must stay cheap
    kl_weight: float = 1e-6  # small: the latent only needs to be smooth, not a prior match
    lidar_loss_weight: float = 1.0
    # Extra L1 weight on camera pixels inside objects' projected boxes (training only). Plain L1 is
    # dominated by sky and road: without it the VAE blurs 10-pixel objects away (MODEL_CARD, "VAE").
    object_loss_weight: float = 9.0
    lidar_no_return_fraction: float = 0.97  # decoded ranges >= this * max_range read as "no return"

    @property
    def downsample(self) -> int:
        return 2 ** len(self.channel_mults)

    def model_settings(self) -> VaeConfig:
        """This config without the training-only ``object_loss_weight``: what decides whether two
        VAEs are interchangeable (same architecture and latent layout)."""
        return replace(self, object_loss_weight=0.0)


@dataclass(frozen=True)
class TextConfig:
    """Text encoder (§3.2, "Text tokens"): default the offline MiniLM sentence encoder."""

    encoder: str = "minilm"  # "minilm" or "hash" (deterministic, dependency-free, for tests)
    dim: int = 384
    max_tokens: int = 32  # prompt tokens kept (padding is masked out)


@dataclass(frozen=True)
class ControlConfig:
    """Control tokenizer (§3.2): sensor, ego, map and object tokens."""

    dim: int = 128  # control-token width fed to the DiT's control cross-attention
    fourier_freqs: int = 6  # NeRF-style frequencies per coordinate
    position_scale_m: float = 50.0  # metres mapped to 1.0 before Fourier embedding
    map_patch: int = 10  # BEV pixels per map-token side
    max_objects: int = 16  # nearest objects kept per frame; the rest are dropped
    crop_size: int = 32  # object reference crops are resized to this square before encoding
    image_feature: str = "vae"  # image-description encoder: pooled VAE-encoder latents
    # False: the geometry-only baseline of the evaluation (MagicDriveV2-style controls): every
    # object token gets the learned nulls for its image and text descriptions, in training and
    # at inference, so only box, category and track reach the model.
    object_descriptions: bool = True


# The decoder's label-map input channels in order (:attr:`LayoutConfig.label_channels`): the classes
# one-hot, the object's paint as RGB, the ground's surface variation, the LiDAR view's nearness.
DECODER_LABEL_CHANNELS = (*LABEL_CLASSES, "paint_red", "paint_green", "paint_blue", "surface", "lidar_nearness")


@dataclass(frozen=True)
class LayoutConfig:
    """Pixel-aligned layout conditioning (:mod:`world_model.model.layout`): per view, at the latent
    resolution, the road, lane lines, road edges, each object's projected box by category group
    and the nearness of the first hit, concatenated to the DiT's input channels beside the noisy
    latent. The map and object tokens stay. Disabled: no extra channels, the paper's tokens alone.

    ``decoder``: the VAE decoder also draws the scene at full resolution, whatever the latents
    keep. Each view's features are modulated at every level (SPADE) by its label map
    (:data:`DECODER_LABEL_CHANNELS`): per pixel the class (sky, off-road, road, markings, objects by
    group), so a lane line or a car lands on its pixels however coarse the latent grid is; the
    object's paint, the unlit albedo of the face it shows, so a red car comes out red with dark
    windows however little of a 10-pixel car's colour the latents keep; the road's and the
    off-road ground's surface variation, so the ground streams past at the ego's speed. The
    modulation also reads the prompt's pooled text embedding per scene class, so the weather and
    the time of day reach every pixel of the sky, the ground and the road whatever colour the
    latents drifted to. The LiDAR view reads the range map the scene implies
    (:func:`~world_model.model.layout.lidar_nearness`), so the returns of a car ahead stand at its
    distance in this frame however far the DiT's range latents lag; the cameras read zeros there.
    The latents stay the encoder's: the ``decoder`` stages fine-tune the decoder alone, and the
    DiTs do not depend on it.

    ``range_head``: the LiDAR is finished at the range map's own resolution by a
    :class:`~world_model.model.range_head.RangeHead` reading the decoder's LiDAR view and the
    range map the scene implies at that resolution, so an object stands with its own edges however
    few columns of the view it had (its stage trains the head alone).

    ``camera_decoder``: the cameras are drawn by a decoder of their own, a copy of ``decoder``
    tuned on the cameras' frames alone (:mod:`world_model.train.camera_decoder_stage`), while the
    LiDAR view keeps ``decoder`` and the range head that finishes it: what the cameras learn moves
    no LiDAR return."""

    enabled: bool = False
    supersample: int = 4  # rays per latent cell side; a channel holds the covered fraction of the cell
    decoder: bool = False
    range_head: bool = False
    camera_decoder: bool = False

    @property
    def channels(self) -> int:
        return len(LAYOUT_CHANNELS) if self.enabled else 0

    @property
    def label_channels(self) -> int:
        """The decoder's label-map input channels (:data:`DECODER_LABEL_CHANNELS`; 0 without ``decoder``)."""
        return len(DECODER_LABEL_CHANNELS) if self.decoder else 0


@dataclass(frozen=True)
class DitConfig:
    """Multi-view + LiDAR diffusion transformer (§3.2)."""

    # Sized for the env's CPU speed target (8 batched envs, 4 denoising steps per chunk): see
    # m4world bench model and m4world bench student. 4.1 M parameters at these values.
    dim: int = 128
    depth: int = 10
    # Depth of the causal student the env runs (None: the teacher's ``depth``). The student does
    # every DiT forward of an env step, so its depth sets the env's speed (m4world bench env);
    # a shallower one starts from evenly spaced teacher blocks (world_model.student.init) while the
    # teacher and the reference model keep all ``depth`` blocks. Fewer blocks trade image quality
    # for speed: long-video tuning can collapse a shallow student's cameras to a grey mean scene.
    student_depth: int | None = None
    # head_dim 64: at these short sequences the softmax's exponentials, not the matmuls, bound CPU
    # attention time, so fewer, wider heads are faster (measured: m4world bench student).
    heads: int = 2
    mlp_ratio: float = 4.0
    patch: int = 2
    cross_view_every: int = 5  # a cross-view attention in blocks 5, 10, ... (1-based)
    in_channels_extra: int = 0  # reference latent + mask channels (§6), 0 = none
    qk_norm_eps: float = 1e-6
    norm_eps: float = 1e-6
    timestep_freq_dim: int = 256  # sinusoidal features of the timestep
    timestep_scale: float = 1000.0  # t in [0, 1] is scaled to the usual diffusion-step range first
    rope_theta: float = 10000.0
    autocast_bf16: bool = True  # trained for bf16 autocast: run in it where bf16 is fast (world_model/precision.py)

    def __post_init__(self) -> None:
        if self.heads < 1 or self.dim % self.heads:
            raise ValueError(f"dit.heads must be a positive divisor of dit.dim ({self.dim}), got {self.heads}")
        if self.depth < 1 or (self.student_depth is not None and not 1 <= self.student_depth <= self.depth):
            raise ValueError(
                f"dit.depth must be >= 1 and dit.student_depth in [1, depth], got {self.depth}, {self.student_depth}"
            )

    @property
    def head_dim(self) -> int:
        return self.dim // self.heads


@dataclass(frozen=True)
class FlowConfig:
    """Rectified flow (§4.1): x_t = (1-t) eps + t x0, t = 1 is data, target v = x0 - eps."""

    timestep_dist: str = "logit_normal"  # or "uniform" (the paper's t ~ U(0, 1))
    logit_mean: float = 0.0
    logit_std: float = 1.0
    shift: float = 1.0  # >1 moves training mass toward noise (SD3-style shift on sigma = 1 - t)
    cond_drop_prob: float = 0.1  # text + controls dropped together, for guidance


@dataclass(frozen=True)
class SamplerConfig:
    """Euler sampling with CFG for cameras and APG for LiDAR (§4.1)."""

    steps: int = 20
    camera_cfg_scale: float = 3.0
    lidar_apg_scale: float = 3.0
    apg_eta: float = 0.0  # weight of the parallel component kept (0 removes it)
    apg_norm_threshold: float = 2.5  # rescale the guidance update to at most this norm
    apg_momentum: float = -0.5  # negative momentum of Sadat et al.


@dataclass(frozen=True)
class ClipConfig:
    """Temporal layout: chunks for the causal student, windows for training."""

    chunk_frames: int = 2  # frames generated per causal chunk (= one env step)
    context_frames: int = 4  # past frames in the student's rolling attention window (not the teacher's)
    train_frames: tuple[int, ...] = (4, 6, 8)  # mixed clip lengths seen by the teacher


@dataclass(frozen=True)
class ModelConfig:
    name: str = "default"
    sensors: SensorConfig = field(default_factory=SensorConfig)
    vae: VaeConfig = field(default_factory=VaeConfig)
    text: TextConfig = field(default_factory=TextConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    dit: DitConfig = field(default_factory=DitConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    sampler: SamplerConfig = field(default_factory=SamplerConfig)
    clip: ClipConfig = field(default_factory=ClipConfig)
    layout: LayoutConfig = field(default_factory=LayoutConfig)

    def __post_init__(self) -> None:
        s, v, d, c = self.sensors, self.vae, self.dit, self.control
        if s.height % v.downsample or s.width % v.downsample:
            raise ValueError(f"image {s.height}x{s.width} must be divisible by the VAE downsampling {v.downsample}")
        if self.latent_hw[0] % d.patch or self.latent_hw[1] % d.patch:
            raise ValueError(f"latent grid {self.latent_hw} must be divisible by the DiT patch {d.patch}")
        if d.dim % d.heads or d.head_dim % 2:
            raise ValueError(f"dit.dim {d.dim} must split into {d.heads} heads of even size")
        bh, bw, _ = s.bev.shape
        if bh % c.map_patch or bw % c.map_patch:
            raise ValueError(f"BEV raster {bh}x{bw} must be divisible by control.map_patch {c.map_patch}")
        if d.cross_view_every < 1:
            raise ValueError("dit.cross_view_every must be >= 1")
        if d.student_depth is not None and not 1 <= d.student_depth <= d.depth:
            raise ValueError(f"dit.student_depth must be in [1, dit.depth={d.depth}] or None, got {d.student_depth}")
        if self.layout.supersample < 1:
            raise ValueError(f"layout.supersample must be >= 1, got {self.layout.supersample}")

    def for_student(self) -> ModelConfig:
        """The causal student's config: ``dit.depth`` = ``dit.student_depth`` (idempotent)."""
        return self.with_depth(self.dit.student_depth or self.dit.depth)

    def with_depth(self, depth: int) -> ModelConfig:
        """This config with a DiT of ``depth`` blocks and no separate student depth."""
        return replace(self, dit=replace(self.dit, depth=depth, student_depth=None))

    def teacher_settings(self) -> ModelConfig:
        """What a bidirectional teacher's weights depend on: this config with the student-only
        settings (``dit.student_depth``, ``clip.context_frames``), the VAE's training-only loss
        weight and the decoder's label maps (the DiTs model the encoder's latents, whatever decodes
        them) neutralized. A teacher trained before a student setting changed stays usable:
        compare teachers under this view."""
        return replace(
            self,
            vae=self.vae.model_settings(),
            layout=without_label_decoder(self).layout,
            dit=replace(self.dit, student_depth=None),
            clip=replace(self.clip, context_frames=0),
        )

    def shared_settings(self) -> ModelConfig:
        """What every model of one family (teacher, student, reference model) shares: the teacher
        settings without the DiT's depth, reference input channels and bf16 autocast (a run-time
        precision that loading rewrites per machine, not a property of the weights)."""
        t = self.teacher_settings()
        return replace(t, dit=replace(t.dit, depth=1, in_channels_extra=0, autocast_bf16=False))

    # -- derived shapes --
    @property
    def latent_hw(self) -> tuple[int, int]:
        return self.sensors.height // self.vae.downsample, self.sensors.width // self.vae.downsample

    @property
    def token_hw(self) -> tuple[int, int]:
        h, w = self.latent_hw
        return h // self.dit.patch, w // self.dit.patch

    @property
    def tokens_per_frame(self) -> int:
        h, w = self.token_hw
        return h * w

    @property
    def map_tokens(self) -> int:
        bh, bw, _ = self.sensors.bev.shape
        return (bh // self.control.map_patch) * (bw // self.control.map_patch)

    @property
    def cross_view_blocks(self) -> tuple[int, ...]:
        """0-based indices of the blocks that carry a cross-view attention."""
        k = self.dit.cross_view_every
        return tuple(i for i in range(self.dit.depth) if (i + 1) % k == 0)

    def latent_shape(self, frames: int) -> tuple[int, int, int, int, int]:
        """(T, V, C, h, w) of one sample's latents."""
        h, w = self.latent_hw
        return frames, self.sensors.num_views, self.vae.latent_channels, h, w

    # -- serialization --
    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["sensors"]["lidar"] = self.sensors.lidar.to_dict()
        d["sensors"]["bev"] = self.sensors.bev.to_dict()
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModelConfig:
        def build(kind: type, values: dict) -> Any:
            unknown = sorted(set(values) - {f.name for f in dataclasses.fields(kind)})
            if unknown:  # a key this code does not know would otherwise be dropped silently
                raise ValueError(f"unknown {kind.__name__} setting(s) {unknown}")
            kw = {}
            for f in dataclasses.fields(kind):
                if f.name not in values:
                    continue
                v = values[f.name]
                kw[f.name] = tuple(v) if isinstance(v, list) else v
            return kind(**kw)

        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"unknown model config section(s) {unknown}")
        s = dict(d["sensors"])
        s["lidar"] = LidarSpec.from_dict(s["lidar"])
        s["bev"] = BevSpec.from_dict(s["bev"])
        return cls(
            name=d["name"],
            sensors=SensorConfig(**s),
            vae=build(VaeConfig, d["vae"]),
            text=build(TextConfig, d["text"]),
            control=build(ControlConfig, d["control"]),
            dit=build(DitConfig, d["dit"]),
            flow=build(FlowConfig, d["flow"]),
            sampler=build(SamplerConfig, d["sampler"]),
            clip=build(ClipConfig, d["clip"]),
            layout=build(LayoutConfig, d["layout"]),
        )


def _tiny() -> ModelConfig:
    # Small enough that a forward/backward on a few frames takes milliseconds.
    return ModelConfig(
        name="tiny",
        sensors=SensorConfig(num_cameras=6, height=16, width=32, bev=BevSpec(m_per_px=4.0)),
        vae=VaeConfig(latent_channels=4, channel_mults=(1, 2), base_channels=8, decoder_base_channels=8),
        text=TextConfig(encoder="hash", dim=32, max_tokens=8),
        control=ControlConfig(dim=32, fourier_freqs=4, map_patch=5, max_objects=4, crop_size=8),
        dit=DitConfig(dim=32, depth=2, student_depth=None, heads=2, patch=1, cross_view_every=2, autocast_bf16=False),
        sampler=SamplerConfig(steps=4),
        clip=ClipConfig(chunk_frames=1, context_frames=2, train_frames=(2, 3)),
    )


def _default() -> ModelConfig:
    return ModelConfig(name="default")


def _gpu() -> ModelConfig:
    # Near the paper's scale (Wan2.1-1.3B-like width/depth, 224x400 views, 16 latent channels).
    return ModelConfig(
        name="gpu",
        sensors=SensorConfig(num_cameras=6, height=224, width=400, bev=BevSpec(m_per_px=0.5)),
        vae=VaeConfig(latent_channels=16, channel_mults=(1, 2, 4), base_channels=64, decoder_base_channels=64),
        text=TextConfig(encoder="minilm", dim=384, max_tokens=128),
        control=ControlConfig(dim=1536, fourier_freqs=8, map_patch=8, max_objects=64, crop_size=64),
        dit=DitConfig(dim=1536, depth=30, student_depth=None, heads=12, patch=2, autocast_bf16=True),
        sampler=SamplerConfig(steps=50, camera_cfg_scale=5.0, lidar_apg_scale=5.0),
        clip=ClipConfig(chunk_frames=3, context_frames=21, train_frames=(13, 29, 45)),
    )


PRESETS = {"tiny": _tiny, "default": _default, "gpu": _gpu}


def with_student_settings(
    cfg: ModelConfig, student_depth: int | None = None, context_frames: int | None = None
) -> ModelConfig:
    """``cfg`` with the student-only settings replaced where given (None keeps the preset's):
    ``dit.student_depth`` and ``clip.context_frames``. A teacher trained under ``cfg`` stays
    usable (:meth:`ModelConfig.teacher_settings`)."""
    if student_depth is not None:
        cfg = replace(cfg, dit=replace(cfg.dit, student_depth=student_depth))
    if context_frames is not None:
        if context_frames < 1:
            raise ValueError(f"context_frames must be >= 1, got {context_frames}")
        cfg = replace(cfg, clip=replace(cfg.clip, context_frames=context_frames))
    return cfg


def with_layout(cfg: ModelConfig, enabled: bool | None) -> ModelConfig:
    """``cfg`` with pixel-aligned layout conditioning switched on or off where given (None keeps
    the preset's): the DiT's layout channels and the decoder's label maps together. The channels
    change the DiT's input, so teacher, student and reference model of one family must agree on it."""
    if enabled is None:
        return cfg
    on = bool(enabled)
    return replace(cfg, layout=replace(cfg.layout, enabled=on, decoder=on))


def without_label_decoder(cfg: ModelConfig) -> ModelConfig:
    """``cfg`` with a plain VAE decoder: the autoencoder the ``vae`` stage trains, and the
    conditions the DiTs train on (they never read the label maps), without a range head."""
    return replace(cfg, layout=replace(cfg.layout, decoder=False, range_head=False, camera_decoder=False))


def with_vae_object_weight(cfg: ModelConfig, weight: float | None) -> ModelConfig:
    """``cfg`` with ``vae.object_loss_weight`` replaced where given (a training-only setting: the
    ``vae`` stage's loss; later stages accept a VAE trained under any value)."""
    if weight is None:
        return cfg
    if not weight >= 0.0:
        raise ValueError(f"the VAE's object loss weight must be >= 0, got {weight}")
    return replace(cfg, vae=replace(cfg.vae, object_loss_weight=float(weight)))


def get_preset(name: str, geometry_only: bool = False) -> ModelConfig:
    """A fresh config for preset ``name`` (one of :data:`PRESETS`); ``geometry_only`` turns off
    object descriptions (the evaluation's baseline, same recipe otherwise)."""
    try:
        cfg = PRESETS[name]()
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}") from None
    return replace(cfg, control=replace(cfg.control, object_descriptions=False)) if geometry_only else cfg
