"""Per-frame spatial VAE shared by camera views and LiDAR range maps (paper §3.2).

Temporal modelling is the DiT's job, so every frame is encoded on its own: one env step can then
be a single frame. Layouts: images are ``(N, 3, H, W)`` floats in [-1, 1]; latents ``(N, C, h, w)``
with ``h = H / downsample``.

LiDAR (§3.2, "LiDAR modality support"): ranges in [0, max_range] metres map linearly to [-1, 1]
and the map is resized to the camera resolution; the single range channel is repeated on the
three image channels so the camera VAE is reused unchanged (decoding averages them).

No return. A ray with no return (``LidarSpec.no_return`` = 0.0) saw nothing within range, so
before normalization it is treated as ``max_range`` (+1.0), *not* as 0 m: 0 m would be the
nearest possible obstacle and resizing would smear it into its neighbours as phantom close
returns. On decoding, ranges at or above ``VaeConfig.lidar_no_return_fraction * max_range`` read back as
``no_return``.

Latent normalization: after VAE training, per-channel mean/std of the posterior means are stored
in buffers so :meth:`SensorVAE.encode` returns roughly unit-variance latents (what rectified
flow expects) and :meth:`SensorVAE.decode` undoes it.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from world_model.model.config import ModelConfig, VaeConfig
from world_model.model.layout import NEARNESS_LEVELS
from world_model.model.range_head import RangeHead
from world_model.observation import ALL_SENSORS, SensorSelection
from world_model.precision import bf16_autocast
from world_model.raster.classes import (
    CLASS_PLANE,
    LABEL_CLASSES,
    MAP_PLANES,
    PAINT_PLANE,
    SCENE_LOOK_CLASSES,
    SURFACE_PLANE,
    decode_paint,
    decode_surface,
)
from world_model.sensors import LidarSpec

# Every paint byte's RGB in [0, 1] (256, 3): the decoder's paint channels are a lookup.
_PAINT_RGB = torch.from_numpy(decode_paint(np.arange(256, dtype=np.uint8)))
# Every surface byte's variation in [-1, 1] (256,): the decoder's surface channel is a lookup.
_SURFACE = torch.from_numpy(decode_surface(np.arange(256, dtype=np.uint8)))


def _groups(channels: int) -> int:
    for g in (8, 4, 2, 1):
        if channels % g == 0:
            return g
    return 1


class ResBlock(nn.Module):
    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.norm1 = nn.GroupNorm(_groups(cin), cin)
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1)
        self.norm2 = nn.GroupNorm(_groups(cout), cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h


class Encoder(nn.Module):
    """(N, 3, H, W) -> mean, logvar (N, C, H/d, W/d)."""

    def __init__(self, cfg: VaeConfig) -> None:
        super().__init__()
        chans = [cfg.base_channels * m for m in cfg.channel_mults]
        self.conv_in = nn.Conv2d(cfg.image_channels, chans[0], 3, padding=1)
        layers: list[nn.Module] = []
        cin = chans[0]
        for c in chans:
            layers += [ResBlock(cin, c), nn.Conv2d(c, c, 3, stride=2, padding=1)]
            cin = c
        layers += [ResBlock(cin, cin), nn.GroupNorm(_groups(cin), cin), nn.SiLU()]
        self.body = nn.Sequential(*layers)
        self.conv_out = nn.Conv2d(cin, 2 * cfg.latent_channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, logvar = self.conv_out(self.body(self.conv_in(x))).chunk(2, dim=1)
        return mean, logvar.clamp(-30.0, 20.0)


class LabelModulation(nn.Module):
    """SPADE (Park et al. 2019) without its hidden layer: features ``x * (1 + gamma) + beta``, with
    gamma and beta a 3x3 convolution of the label map's channels (the classes one-hot, then the
    objects' paint as RGB and the ground's surface when the decoder reads them) area-pooled to the
    features' grid.

    With ``style_dim``, gamma and beta also get, at each pixel, its label class's vector read from
    the scene's style (the prompt's pooled text embedding) by a linear map: how that class looks in
    this weather and light. Zero-initialized, so a decoder fine-tuned with it starts as the plain one."""

    def __init__(self, label_channels: int, channels: int, style_dim: int = 0) -> None:
        super().__init__()
        self.conv = nn.Conv2d(label_channels, 2 * channels, 3, padding=1)
        styled = min(label_channels, len(SCENE_LOOK_CLASSES))
        self.style = nn.Linear(style_dim, styled * 2 * channels) if style_dim else None
        for layer in (self.conv, self.style):
            if layer is not None:
                nn.init.zeros_(layer.weight)
                nn.init.zeros_(layer.bias)

    def forward(self, x: torch.Tensor, labels: torch.Tensor, style: torch.Tensor | None = None) -> torch.Tensor:
        """x (N, c, h, w), labels (N, K, H, W) channels, the classes' one-hot first (H, W multiples of
        h, w), style (N, S) -> (N, c, h, w)."""
        if labels.shape[-2:] != x.shape[-2:]:
            # The area mean over whole cells: adaptive_avg_pool2d's result bit for bit, in half its time on CPU.
            labels = F.avg_pool2d(labels, (labels.shape[-2] // x.shape[-2], labels.shape[-1] // x.shape[-1]))
        labels = labels.to(x.dtype)
        mod = self.conv(labels)
        if self.style is not None:
            per_class = self.style(style.to(x.dtype)).view(len(x), -1, mod.shape[1])  # (N, Ks, 2c)
            mod = mod + torch.einsum("nkhw,nkc->nchw", labels[:, : per_class.shape[1]], per_class)
        gamma, beta = mod.chunk(2, dim=1)
        return x * (1.0 + gamma) + beta


# The weights a label-drawing decoder has beyond the plain one's (which it starts from).
LABEL_DECODER_WEIGHTS = ("decoder.label_mods.", "decoder.nearness_gate.")


class Decoder(nn.Module):
    """(N, C, h, w) -> (N, 3, h*d, w*d). Channels shrink as resolution grows to keep decoding cheap.

    With ``label_channels``, a :class:`LabelModulation` after the input convolution and after each
    level's normalization draws the view's label map (N, K, H, W) into the features, in the scene's
    style (N, ``style_dim``) when that is given. With ``nearness_gate`` the last label channel is the
    LiDAR view's nearness map, which the output also moves toward by a learned per-pixel share."""

    def __init__(
        self, cfg: VaeConfig, label_channels: int = 0, style_dim: int = 0, nearness_gate: bool = False
    ) -> None:
        super().__init__()
        if nearness_gate and not label_channels:
            raise ValueError("the nearness gate reads the label channels' last one: give label_channels")
        chans = [cfg.decoder_base_channels * m for m in reversed(cfg.channel_mults)]
        self.conv_in = nn.Conv2d(cfg.latent_channels, chans[0], 3, padding=1)
        self.mid = ResBlock(chans[0], chans[0])
        ups: list[nn.Module] = []
        cin = chans[0]
        for c in chans:
            # One conv per level after nearest upsampling: the full-resolution levels dominate cost.
            ups += [
                nn.Upsample(scale_factor=2.0, mode="nearest"),
                nn.Conv2d(cin, c, 3, padding=1),
                nn.GroupNorm(_groups(c), c),
                nn.SiLU(),
            ]
            cin = c
        self.up = nn.Sequential(*ups)
        self.conv_out = nn.Conv2d(cin, cfg.image_channels, 3, padding=1)
        self.label_mods = (
            nn.ModuleList(LabelModulation(label_channels, c, style_dim) for c in (chans[0], *chans))
            if label_channels
            else None
        )
        self.style_dim = style_dim
        # Where the last label channel (the LiDAR view's nearness) puts a surface in range, the
        # output moves toward the range it implies by a learned share: the modulations alone shift
        # the latent's returns by a fraction of where the scene moved them. Zero-initialized: the
        # share starts at 0 and the decoder draws as it did; torch.clamp passes the gradient at its
        # bounds, so it can grow from there.
        self.nearness_gate = nn.Conv2d(cin + 1, 1, 3, padding=1) if nearness_gate else None
        if self.nearness_gate is not None:
            nn.init.zeros_(self.nearness_gate.weight)
            nn.init.zeros_(self.nearness_gate.bias)

    def forward(
        self, z: torch.Tensor, labels: torch.Tensor | None = None, style: torch.Tensor | None = None
    ) -> torch.Tensor:
        """z (N, C, h, w); ``labels`` (N, K, H, W) channels (:meth:`SensorVAE._label_inputs`), required
        with label modulation (all zeros: no layout, e.g. the LiDAR view); ``style`` (N, S), required
        with ``style_dim``."""
        if self.label_mods is None:
            return self.conv_out(self.up(self.mid(self.conv_in(z))))
        if labels is None:
            raise ValueError("this decoder draws each view's label map: pass labels")
        if self.style_dim and (style is None or tuple(style.shape) != (len(z), self.style_dim)):
            got = None if style is None else tuple(style.shape)
            raise ValueError(
                f"this decoder draws the scene's style: pass style ({len(z)}, {self.style_dim}), got {got}"
            )
        mods = iter(self.label_mods)
        h = self.mid(next(mods)(self.conv_in(z), labels, style))
        layers = list(self.up)
        for i in range(0, len(layers), 4):  # upsample, conv, norm | modulation | activation
            upsample, conv, norm, act = layers[i : i + 4]
            h = act(next(mods)(norm(conv(upsample(h))), labels, style))
        out = self.conv_out(h)
        if self.nearness_gate is None:
            return out
        near = labels[:, -1:]
        share = torch.clamp(self.nearness_gate(torch.cat([h, near], dim=1)), 0.0, 1.0) * (near > 0)
        return out + share * ((1.0 - 2.0 * near) - out)  # 1 - 2 * nearness: the range's image value


class SensorVAE(nn.Module):
    """The shared autoencoder plus sensor-specific (de)normalization."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg.vae)
        draws = cfg.layout.decoder
        self.decoder = Decoder(cfg.vae, cfg.layout.label_channels, cfg.text.dim if draws else 0, nearness_gate=draws)
        if cfg.layout.camera_decoder and not draws:
            raise ValueError("a camera decoder of its own is a label decoder's copy: it needs layout.decoder")
        self.camera_decoder = (
            Decoder(cfg.vae, cfg.layout.label_channels, cfg.text.dim) if cfg.layout.camera_decoder else None
        )
        self.range_head = RangeHead() if cfg.layout.range_head else None
        c = cfg.vae.latent_channels
        self.register_buffer("latent_mean", torch.zeros(c))
        self.register_buffer("latent_std", torch.ones(c))

    # -- raw autoencoder --
    def posterior(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Unnormalized posterior mean/logvar of (N, 3, H, W) images."""
        return self.encoder(images)

    def decode_raw(
        self,
        z: torch.Tensor,
        labels: torch.Tensor | None = None,
        style: torch.Tensor | None = None,
        nearness: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Unnormalized latents (N, C, h, w) -> images; ``labels``, ``style`` and ``nearness`` as :meth:`decode`."""
        return self.decoder(z, self._label_inputs(labels, z, nearness), self._style(style, labels, z))

    @property
    def draws_labels(self) -> bool:
        """Whether the decoder draws the scene (``layout.decoder``): it needs each camera's label
        map, the scene's style and the LiDAR view's nearness map."""
        return self.decoder.label_mods is not None

    def _style(
        self, style: torch.Tensor | None, labels: torch.Tensor | None, like: torch.Tensor
    ) -> torch.Tensor | None:
        """(N, S) style for the decoder: required with label maps, zeros without (nothing to style)."""
        if not self.draws_labels:
            return None
        if style is None:
            if labels is not None:
                raise ValueError("this VAE's decoder draws the label maps in the scene's style: pass style")
            return like.new_zeros(like.shape[0], self.decoder.style_dim)
        return style.to(device=like.device, dtype=like.dtype)

    def _label_inputs(
        self, labels: torch.Tensor | None, like: torch.Tensor, nearness: torch.Tensor | None = None
    ) -> torch.Tensor | None:
        """(N, 3, H, W) uint8 label maps (class ids, paint, surface: :meth:`LabelRasterizer.maps`) and
        (N, H, W) uint8 nearness maps (:func:`~world_model.model.layout.lidar_nearness`) ->
        (N, K, H, W), the channels of :data:`~world_model.model.config.DECODER_LABEL_CHANNELS`: the
        :data:`~world_model.raster.classes.LABEL_CLASSES` one-hot (:data:`~world_model.raster.classes.NO_LABEL`
        and None -> all zeros: no layout), then the paint as RGB in [0, 1], then the surface
        variation in [-1, 1], then the nearness in [0, 1] (None -> zeros, a camera's). None for a
        decoder without label modulation."""
        if not self.draws_labels:
            return None
        classes = len(LABEL_CLASSES)
        h, w = self.cfg_hw
        n = like.shape[0]
        channels = []
        if labels is None:  # every channel but the nearness
            channels.append(like.new_zeros(n, self.cfg.layout.label_channels - 1, h, w))
        else:
            if labels.shape != (n, MAP_PLANES, h, w):
                raise ValueError(
                    f"labels must be {(n, MAP_PLANES, h, w)} class ids, paint and surface, got {tuple(labels.shape)}"
                )
            labels = labels.to(like.device).long()
            ids = labels[:, CLASS_PLANE].clamp(max=classes)  # NO_LABEL -> the dropped extra class
            channels.append(F.one_hot(ids, classes + 1)[..., :classes].movedim(-1, 1).to(like.dtype))
            rgb = _PAINT_RGB.to(device=like.device, dtype=like.dtype)[labels[:, PAINT_PLANE]]
            channels.append(rgb.movedim(-1, 1))
            channels.append(_SURFACE.to(device=like.device, dtype=like.dtype)[labels[:, SURFACE_PLANE]][:, None])
        if nearness is None:
            channels.append(like.new_zeros(n, 1, h, w))
        elif nearness.shape != (n, h, w):
            raise ValueError(f"nearness must be {(n, h, w)} uint8 maps, got {tuple(nearness.shape)}")
        else:
            channels.append(nearness.to(device=like.device, dtype=like.dtype)[:, None] / NEARNESS_LEVELS)
        return torch.cat(channels, dim=1)

    # -- normalized latents (what the DiT sees) --
    def _norm(self, z: torch.Tensor) -> torch.Tensor:
        return (z - self.latent_mean[:, None, None]) / self.latent_std[:, None, None]

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) in [-1, 1] -> normalized latent means (N, C, h, w)."""
        return self._norm(self.encoder(images)[0])

    def decode(
        self,
        latents: torch.Tensor,
        labels: torch.Tensor | None = None,
        style: torch.Tensor | None = None,
        nearness: torch.Tensor | None = None,
        lidar: bool | torch.Tensor = False,
    ) -> torch.Tensor:
        """Normalized latents (N, C, h, w) -> images (N, 3, H, W), roughly in [-1, 1].

        ``labels``: (N, 3, H, W) uint8 label maps (class ids, paint, surface), read when the decoder draws them
        (:attr:`draws_labels`); None there means no layout (the LiDAR view). ``style``: (N, S) the
        scene's style (:func:`~world_model.model.conditions.prompt_style`), required with labels
        when the decoder draws them. ``nearness``: (N, H, W) uint8, the LiDAR view's range map the
        scene implies, read when the decoder draws the labels; None there means none (a camera).
        ``lidar``: whether the latents are the LiDAR view's, True/False for all or (N,) bool per
        latent, on the CPU: the LiDAR view is drawn by :attr:`decoder`, a camera by
        :attr:`camera_decoder` when the VAE has one (``layout.camera_decoder``)."""
        z = latents * self.latent_std[:, None, None] + self.latent_mean[:, None, None]
        # Channels-last input: oneDNN's CPU convolutions for these few channels run about twice as
        # fast in NHWC (m4world bench model's vae_decode_ms_per_frame); same values to ~1e-6.
        z = z.contiguous(memory_format=torch.channels_last)
        inputs, style = self._label_inputs(labels, z, nearness), self._style(style, labels, z)
        if self.camera_decoder is None:
            return self.decoder(z, inputs, style)
        is_lidar = torch.as_tensor(lidar, dtype=torch.bool).expand(len(z))
        if bool(is_lidar.all()) or not bool(is_lidar.any()):
            return (self.decoder if bool(is_lidar.all()) else self.camera_decoder)(z, inputs, style)
        drawn = []
        for decoder, rows in ((self.camera_decoder, ~is_lidar), (self.decoder, is_lidar)):
            index = rows.nonzero()[:, 0].to(z.device)
            drawn.append((index, decoder(z[index], inputs[index], style[index])))
        out = drawn[0][1].new_empty(len(z), *drawn[0][1].shape[1:])
        for index, images in drawn:
            out.index_copy_(0, index, images.to(out.dtype))
        return out

    @torch.no_grad()
    def set_latent_stats(self, images: torch.Tensor) -> None:
        """Fit the per-channel latent normalization on a sample of (N, 3, H, W) images."""
        mean = self.encoder(images)[0].transpose(0, 1).flatten(1)
        self.latent_mean.copy_(mean.mean(dim=1))
        self.latent_std.copy_(mean.std(dim=1).clamp_min(1e-4))

    # -- whole observations --
    @torch.no_grad()
    def encode_frames(self, cameras: np.ndarray, lidar: np.ndarray, batch: int = 64) -> torch.Tensor:
        """cameras uint8 (T, V, H, W, 3) + lidar metres (T, beams, azimuth) -> latents (T, V+1, C, h, w)."""
        t, v = cameras.shape[:2]
        device = self.latent_mean.device
        images = torch.cat(
            [
                cameras_to_images(cameras.reshape(t * v, *cameras.shape[2:]), device).reshape(
                    t, v, 3, *cameras.shape[2:4]
                ),
                lidar_to_images(lidar, self.cfg, device)[:, None],
            ],
            dim=1,
        )
        flat = images.flatten(0, 1)
        out = torch.cat([self.encode(flat[i : i + batch]) for i in range(0, len(flat), batch)])
        return out.reshape(t, v + 1, *out.shape[1:])

    @torch.no_grad()
    def decode_frames(
        self,
        latents: torch.Tensor,
        lidar_spec: LidarSpec | None = None,
        labels: np.ndarray | torch.Tensor | None = None,
        style: np.ndarray | torch.Tensor | None = None,
        nearness: np.ndarray | torch.Tensor | None = None,
        sensors: SensorSelection = ALL_SENSORS,
        range_nearness: np.ndarray | torch.Tensor | None = None,
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """latents (T, V+1, C, h, w) -> cameras uint8 (T, V, H, W, 3), lidar metres (T, beams, azimuth);
        a sensor left out of ``sensors`` is not decoded and comes back None.

        ``labels``: the frames' camera label maps (T, V, 3, H, W) uint8 and ``style``: the scene's
        style, (S,) for every frame or (T, S), required to decode the cameras when the decoder draws
        them (:attr:`draws_labels`; the conditions carry them, ``ConditionArrays.labels``,
        ``ConditionArrays.style``). ``nearness``: the LiDAR view's nearness maps (T, H, W) uint8,
        required to decode the LiDAR then (``ConditionArrays.lidar_nearness``). ``range_nearness``:
        the same at the range map's resolution (T, beams, azimuth) uint8, required to decode the
        LiDAR with a :attr:`range_head` (``ConditionArrays.range_nearness``)."""
        t, v1 = latents.shape[:2]
        latents = latents.float()
        cams = lid = cam_labels = cam_style = lidar_near = None
        if self.draws_labels and sensors.cameras:  # the maps checked before any decoding
            cam_labels, cam_style = self._camera_maps(t, v1 - 1, labels, style, latents.device)
        if self.draws_labels and sensors.lidar:
            lidar_near = self._nearness_maps(t, nearness, latents.device)
        if sensors.cameras:
            # Cameras end as uint8: decoding them in bf16 (~2x faster on CPU, with the DiT's bf16
            # switch) moves a pixel by a few levels at most. Ranges need fp32: the LiDAR view is decoded apart.
            with bf16_autocast(latents.device.type, self.cfg.dit.autocast_bf16):
                images = self.decode(latents[:, :-1].flatten(0, 1), cam_labels, cam_style)
            cams = images_to_cameras(images.reshape(t, v1 - 1, 3, *self.cfg_hw))
        if sensors.lidar:
            lid = self._decode_lidar(latents[:, -1], lidar_near, range_nearness, lidar_spec or self.cfg.sensors.lidar)
        return cams, lid

    def _decode_lidar(
        self,
        latents: torch.Tensor,
        nearness: torch.Tensor | None,
        range_nearness: np.ndarray | torch.Tensor | None,
        spec: LidarSpec,
    ) -> np.ndarray:
        """The LiDAR view's latents (T, C, h, w) -> metres (T, beams, azimuth): the view decoded,
        then finished at the range map's resolution by the :attr:`range_head` when there is one."""
        view = self.decode(latents, nearness=nearness, lidar=True)
        fraction = self.cfg.vae.lidar_no_return_fraction
        if self.range_head is None:
            return images_to_lidar(view, spec, fraction)
        want = (len(latents), spec.beams, spec.azimuth)
        if range_nearness is None or tuple(range_nearness.shape) != want:
            got = None if range_nearness is None else tuple(range_nearness.shape)
            raise ValueError(
                f"this VAE's range head draws the scene's range map: need range_nearness {want}, got {got}"
            )
        near = torch.as_tensor(range_nearness, device=latents.device)
        return image_values_to_ranges(
            self.range_head(view.float().mean(dim=1, keepdim=True), near)[:, 0], spec, fraction
        )

    def _camera_maps(
        self,
        t: int,
        cameras: int,
        labels: np.ndarray | torch.Tensor | None,
        style: np.ndarray | torch.Tensor | None,
        device: torch.device,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`decode_frames`'s camera maps of ``t`` frames checked and flattened for
        :meth:`decode`: the label maps (T * cameras, 3, H, W) uint8 and the style (T * cameras, S)."""
        s = self.decoder.style_dim
        if style is None or tuple(style.shape) not in ((s,), (t, s)):
            got = None if style is None else tuple(style.shape)
            raise ValueError(f"this VAE's decoder draws the scene's style: need style ({s},) or ({t}, {s}), got {got}")
        per_frame = torch.as_tensor(style, dtype=torch.float32, device=device).expand(t, s)
        if labels is None or tuple(labels.shape[:2]) != (t, cameras):
            got = None if labels is None else tuple(labels.shape)
            raise ValueError(
                f"this VAE's decoder draws each camera's label map: "
                f"need labels ({t}, {cameras}, {MAP_PLANES}, H, W), got {got}"
            )
        cam_labels = torch.as_tensor(labels, device=device).flatten(0, 1)  # uint8: the small copy
        return cam_labels, per_frame.repeat_interleave(cameras, dim=0)

    def _nearness_maps(self, t: int, nearness: np.ndarray | torch.Tensor | None, device: torch.device) -> torch.Tensor:
        """:meth:`decode_frames`'s LiDAR nearness maps of ``t`` frames, checked: (T, H, W) uint8."""
        if nearness is None or tuple(nearness.shape) != (t, *self.cfg_hw):
            got = None if nearness is None else tuple(nearness.shape)
            raise ValueError(
                f"this VAE's decoder draws the LiDAR view's nearness: need nearness ({t}, {self.cfg_hw[0]}, "
                f"{self.cfg_hw[1]}), got {got}"
            )
        return torch.as_tensor(nearness, device=device)

    def reconstruct_frames(
        self,
        cameras: np.ndarray,
        lidar: np.ndarray,
        labels: np.ndarray | None = None,
        style: np.ndarray | None = None,
        nearness: np.ndarray | None = None,
        range_nearness: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """cameras uint8 (T, V, H, W, 3) + lidar metres (T, beams, azimuth) through the autoencoder
        and back, same layouts: the best any model generating through this VAE can render.
        ``labels``, ``style``, ``nearness`` and ``range_nearness`` as :meth:`decode_frames`."""
        latents = self.encode_frames(np.asarray(cameras), np.asarray(lidar, np.float32))
        return self.decode_frames(latents, labels=labels, style=style, nearness=nearness, range_nearness=range_nearness)

    @property
    def cfg_hw(self) -> tuple[int, int]:
        return self.cfg.sensors.height, self.cfg.sensors.width


def weighted_l1(reconstruction: torch.Tensor, target: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Per-image weighted mean absolute error (N,) of (N, 3, H, W) images under (N, 1, H, W) pixel
    weights; normalized by the weights' sum, so all-ones weights give the plain per-image L1."""
    err = ((reconstruction - target).abs() * weights).sum(dim=(1, 2, 3))
    return err / (weights.sum(dim=(1, 2, 3)) * reconstruction.shape[1])


def kl_loss(mean: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(q || N(0, I)), averaged over elements."""
    return 0.5 * (mean.pow(2) + logvar.exp() - 1.0 - logvar).mean()


# -- sensor normalization --------------------------------------------------------------------


def cameras_to_images(cameras: np.ndarray | torch.Tensor, device: torch.device | str | None = None) -> torch.Tensor:
    """uint8 (..., H, W, 3) -> float32 (..., 3, H, W) in [-1, 1], on ``device`` (None: the input's)."""
    if isinstance(cameras, np.ndarray) and not cameras.flags.writeable:
        cameras = np.array(cameras)  # memory-mapped clips are read-only; torch wants writable memory
    x = torch.as_tensor(cameras, device=device)
    if x.dtype != torch.uint8 or x.shape[-1] != 3:
        raise ValueError(f"cameras must be uint8 (..., H, W, 3), got {x.dtype} {tuple(x.shape)}")
    return x.movedim(-1, -3).float() / 127.5 - 1.0


def images_to_cameras(images: torch.Tensor) -> np.ndarray:
    """float (..., 3, H, W) in [-1, 1] -> uint8 (..., H, W, 3)."""
    x = ((images.float().clamp(-1, 1) + 1.0) * 127.5).round().to(torch.uint8)
    return x.movedim(-3, -1).cpu().numpy()


def lidar_to_images(
    ranges: np.ndarray | torch.Tensor, cfg: ModelConfig, device: torch.device | str | None = None
) -> torch.Tensor:
    """Range maps metres (..., beams, azimuth) -> (..., 3, H, W) in [-1, 1] at the view resolution,
    on ``device`` (None: the input's)."""
    spec = cfg.sensors.lidar
    if isinstance(ranges, torch.Tensor):
        r = ranges.float().to(device or ranges.device)
    else:
        r = torch.as_tensor(np.asarray(ranges, np.float32), device=device)
    if r.ndim < 2:
        raise ValueError(f"lidar must be (..., beams, azimuth), got shape {tuple(r.shape)}")
    x = ranges_to_image_values(r, spec)
    lead = x.shape[:-2]
    x = x.reshape(-1, 1, *x.shape[-2:])
    # Antialiased bilinear: azimuth is decimated (1024 -> 112) while beams are upsampled (32 -> 64).
    x = F.interpolate(
        x, size=(cfg.sensors.height, cfg.sensors.width), mode="bilinear", antialias=True, align_corners=False
    ).clamp(-1.0, 1.0)
    return x.expand(-1, 3, -1, -1).reshape(*lead, 3, cfg.sensors.height, cfg.sensors.width).contiguous()


def ranges_to_image_values(ranges: torch.Tensor, spec: LidarSpec) -> torch.Tensor:
    """Range maps in metres (..., beams, azimuth) -> image values in [-1, 1] at the same
    resolution: 0 m at -1, ``max_range`` at +1, a ray without a return at +1 (nothing within range)."""
    r = torch.where(ranges <= spec.no_return, torch.full_like(ranges, spec.max_range), ranges)
    return r.clamp(0.0, spec.max_range) / spec.max_range * 2.0 - 1.0


def images_to_lidar(images: torch.Tensor, spec: LidarSpec, no_return_fraction: float) -> np.ndarray:
    """(..., 3, H, W) in [-1, 1] -> float32 metres (..., beams, azimuth), no-return restored."""
    x = images.float().mean(dim=-3)
    lead = x.shape[:-2]
    x = F.interpolate(
        x.reshape(-1, 1, *x.shape[-2:]), size=(spec.beams, spec.azimuth), mode="bilinear", align_corners=False
    )
    return image_values_to_ranges(x.reshape(*lead, spec.beams, spec.azimuth), spec, no_return_fraction)


def image_values_to_ranges(values: torch.Tensor, spec: LidarSpec, no_return_fraction: float) -> np.ndarray:
    """Range maps in image values (..., beams, azimuth), [-1, 1] -> float32 metres, no-return restored."""
    r = (values.float().clamp(-1, 1) + 1.0) * 0.5 * spec.max_range
    r = torch.where(r >= no_return_fraction * spec.max_range, torch.full_like(r, spec.no_return), r)
    return r.detach().cpu().numpy().astype(np.float32)
