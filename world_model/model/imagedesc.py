"""Image-description encoders: an object's reference crop -> one appearance feature (§3.2).

The paper uses SigLIP-2. Here the default is the model's own VAE encoder, mean- and std-pooled
over space, followed (inside the control tokenizer) by a learned projection. Why not SigLIP-2:
it would add a ~400M-parameter dependency and several hundred ms per crop on this CPU, and no
offline copy ships with the project; the VAE encoder is already loaded, was trained on the same
imagery, and its pooled latents keep colour and coarse shape, which is what the procedural
scenes vary. The trade-off is semantics: pooled VAE features do not know that a "tree truck" is
a truck. Plug another encoder in by implementing :class:`ImageDescriptionEncoder` (its ``dim``
must equal :func:`image_feature_dim`).
"""

from __future__ import annotations

import hashlib
from abc import ABC, abstractmethod

import numpy as np
import torch
import torch.nn.functional as F

from world_model.model.config import ModelConfig
from world_model.model.vae import SensorVAE, cameras_to_images


def image_feature_dim(cfg: ModelConfig) -> int:
    """Width of the image-description feature the tokenizer expects."""
    if cfg.control.image_feature == "vae":
        return 2 * cfg.vae.latent_channels
    raise ValueError(f"unknown control.image_feature {cfg.control.image_feature!r}; supported: 'vae'")


class ImageDescriptionEncoder(ABC):
    """uint8 crops (h, w, 3) of any size -> float32 (N, dim) features, cached by content; each crop's
    feature is independent of the others encoded with it."""

    dim: int

    def __init__(self) -> None:
        self._cache: dict[bytes, np.ndarray] = {}

    def encode(self, crops: list[np.ndarray]) -> np.ndarray:
        keys = []
        for c in crops:
            c = np.ascontiguousarray(c)
            if c.dtype != np.uint8 or c.ndim != 3 or c.shape[2] != 3:
                raise ValueError(f"a reference crop must be uint8 (h, w, 3), got {c.dtype} {c.shape}")
            keys.append(hashlib.sha1(c.tobytes() + str(c.shape).encode()).digest())
        todo = {k: c for k, c in zip(keys, crops, strict=True) if k not in self._cache}
        for k, c in todo.items():
            # One crop per call: batched, the encoder's convolutions would give a crop low bits that
            # depend on which other crops were new with it (a rollout would depend on its batch
            # neighbours and on which process encoded what first).
            (self._cache[k],) = np.asarray(self._encode([c]), dtype=np.float32)
        if not crops:
            return np.zeros((0, self.dim), np.float32)
        return np.stack([self._cache[k] for k in keys])

    def clear_cache(self) -> None:
        """Call after the underlying network changed."""
        self._cache.clear()

    @abstractmethod
    def _encode(self, crops: list[np.ndarray]) -> np.ndarray: ...


class VaeCropEncoder(ImageDescriptionEncoder):
    """Pooled VAE-encoder latents of the crop resized to ``control.crop_size`` squared."""

    def __init__(self, vae: SensorVAE) -> None:
        super().__init__()
        self.vae = vae
        self.size = vae.cfg.control.crop_size
        self.dim = image_feature_dim(vae.cfg)

    @torch.no_grad()
    def _encode(self, crops: list[np.ndarray]) -> np.ndarray:
        device = self.vae.latent_mean.device
        images = torch.stack(
            [
                F.interpolate(
                    cameras_to_images(c, device)[None],
                    size=(self.size, self.size),
                    mode="bilinear",
                    antialias=True,
                    align_corners=False,
                )[0]
                for c in crops
            ]
        )
        z = self.vae.encode(images)  # (N, C, s/d, s/d)
        return torch.cat([z.mean(dim=(2, 3)), z.std(dim=(2, 3), unbiased=False)], dim=1).cpu().numpy()
