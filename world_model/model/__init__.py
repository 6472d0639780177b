"""The neural world model (paper §3.1-§4.1): VAE, control tokenizer, multi-view DiT, flow, sampling."""

from world_model.model.conditions import (
    ConditionArrays,
    ConditionOptions,
    Conditions,
    build_condition_arrays,
    view_adjacency,
)
from world_model.model.config import (
    ClipConfig,
    ControlConfig,
    DitConfig,
    FlowConfig,
    ModelConfig,
    SamplerConfig,
    SensorConfig,
    TextConfig,
    VaeConfig,
    get_preset,
)
from world_model.model.dit import MultiViewDiT
from world_model.model.flow import denoise_step, euler_sample, flow_matching_loss, sample_timesteps
from world_model.model.guidance import AdaptiveProjectedGuidance, cfg_combine
from world_model.model.imagedesc import ImageDescriptionEncoder, VaeCropEncoder
from world_model.model.sampler import GuidedVelocity, generate, latents_to_observations, sample_latents
from world_model.model.text import HashTextEncoder, MiniLMTextEncoder, TextEncoder, make_text_encoder
from world_model.model.tokens import ControlTokenizer, ControlTokens
from world_model.model.vae import SensorVAE

__all__ = [
    "AdaptiveProjectedGuidance",
    "ClipConfig",
    "ConditionArrays",
    "ConditionOptions",
    "Conditions",
    "ControlConfig",
    "ControlTokenizer",
    "ControlTokens",
    "DitConfig",
    "FlowConfig",
    "GuidedVelocity",
    "HashTextEncoder",
    "ImageDescriptionEncoder",
    "MiniLMTextEncoder",
    "ModelConfig",
    "MultiViewDiT",
    "SamplerConfig",
    "SensorConfig",
    "SensorVAE",
    "TextConfig",
    "TextEncoder",
    "VaeConfig",
    "VaeCropEncoder",
    "build_condition_arrays",
    "cfg_combine",
    "denoise_step",
    "euler_sample",
    "flow_matching_loss",
    "generate",
    "get_preset",
    "latents_to_observations",
    "make_text_encoder",
    "sample_latents",
    "sample_timesteps",
    "view_adjacency",
]
