"""What turns a rollout's SceneFrames into the world model's condition arrays, without the DiTs.

The world model holds one :class:`ConditionBuilder`; so does each simulation worker of a vector
env (:mod:`m4world_env.workers`), built from the model's config and VAE weights, so the CPU side
of a step can run beside the model, in another process, by the same code.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from world_model.model.conditions import ConditionArrays, ConditionOptions, build_condition_arrays, style_of_prompt
from world_model.model.config import ModelConfig
from world_model.model.imagedesc import ImageDescriptionEncoder, VaeCropEncoder
from world_model.model.text import TextEncoder, make_text_encoder
from world_model.model.vae import SensorVAE
from world_model.observation import ALL_SENSORS, SensorSelection
from world_model.raster.maps import SceneRaster
from world_model.scene import SceneFrame, ScenePrompt
from world_model.sim import ProceduralSimulator


class ConditionBuilder:
    """The map raster, the text encoder, the image-description encoder and the scene raster (the
    decoder's maps, :class:`~world_model.raster.maps.SceneRaster`) of a model config."""

    def __init__(self, cfg: ModelConfig, text: TextEncoder, image: ImageDescriptionEncoder) -> None:
        self.cfg, self.text, self.image = cfg, text, image
        self._bev = ProceduralSimulator(bev=cfg.sensors.bev)  # the map condition is a BEV raster
        self.raster = SceneRaster(cfg)

    @classmethod
    def from_vae_weights(cls, cfg: ModelConfig, vae_weights: Mapping[str, np.ndarray]) -> ConditionBuilder:
        """A builder with its own text encoder and a CPU copy of the VAE (for the crops' features),
        given the VAE's state dict as numpy arrays (what a process without the model receives)."""
        vae = SensorVAE(cfg)
        vae.load_state_dict({k: torch.from_numpy(np.asarray(v)) for k, v in vae_weights.items()})
        vae.eval().requires_grad_(False)
        return cls(cfg, make_text_encoder(cfg.text), VaeCropEncoder(vae))

    @property
    def chunk_frames(self) -> int:
        return self.cfg.clip.chunk_frames

    def bev(self, frame: SceneFrame) -> np.ndarray:
        """The BEV map raster the model is conditioned on, (h, w, c) uint8."""
        return self._bev.render_bev(frame)

    def style(self, prompt: ScenePrompt) -> np.ndarray:
        """(Dt,) the scene style the decoder reads for ``prompt`` (:func:`style_of_prompt`)."""
        return style_of_prompt(prompt, self.cfg, self.text)

    def arrays(
        self,
        frames: Sequence[SceneFrame],
        first: SceneFrame,
        crops: Mapping[str, np.ndarray] | None = None,
        crop_since: Mapping[str, int] | None = None,
        labeled: Sequence[bool] | None = None,
        sensors: SensorSelection = ALL_SENSORS,
    ) -> ConditionArrays:
        """Conditions of ``frames`` of a rollout that started at ``first`` (ego pose reference, §3.2);
        ``crops`` by track id, each from frame ``crop_since[track]`` on (absent: every frame);
        ``labeled``: the frames whose label map the decoder will draw (default: all), of the
        ``sensors`` it will decode (:attr:`ConditionOptions.sensors`)."""
        bev = np.stack([self.bev(f) for f in frames])
        options = ConditionOptions(
            image_encoder=self.image,
            crops=dict(crops or {}),
            crop_since=crop_since,
            first_ego=first.ego,
            raster=self.raster,
            labeled=labeled,
            sensors=sensors,
        )
        return build_condition_arrays(frames, bev, self.cfg, self.text, options)

    def chunk_arrays(
        self,
        chunk: Sequence[SceneFrame],
        first: SceneFrame,
        crops: Mapping[str, np.ndarray] | None = None,
        crop_since: Mapping[str, int] | None = None,
        every_frame: bool = True,
        sensors: SensorSelection = ALL_SENSORS,
    ) -> list[ConditionArrays]:
        """:meth:`arrays` of a step's frames, one per causal chunk of :attr:`chunk_frames` frames (the
        student's unit); ``len(chunk)`` must be a multiple of it. Without ``every_frame`` only the
        step's last frame is decoded (:class:`~world_model.rollout.batch.RolloutBatch`), so only it
        gets a label map; only the ``sensors`` decoded get theirs."""
        if not chunk or len(chunk) % self.chunk_frames:
            raise ValueError(f"a step's frames must be a positive multiple of {self.chunk_frames}, got {len(chunk)}")
        last = len(chunk) - 1
        return [
            self.arrays(
                chunk[k : k + self.chunk_frames],
                first,
                crops,
                crop_since,
                None if every_frame else [k + j == last for j in range(self.chunk_frames)],
                sensors,
            )
            for k in range(0, len(chunk), self.chunk_frames)
        ]
