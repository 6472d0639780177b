"""The default judge backend's networks: a crop network and a scene network (small CNNs).

``CropNet`` reads one object crop (3, S, S) plus its native-resolution statistics and gives
category logits (``CATEGORIES`` + background), colour logits (``NAMED_COLORS``), a clarity logit
and a unit embedding; two embeddings are compared by :meth:`CropNet.same_logit` (visual fidelity,
cross-view consistency). ``SceneNet`` reads a multi-view frame (V, 3, H, W), encodes each view with
one shared trunk, averages over views, and gives weather and time-of-day logits; its pooled
features are the "judge features" of the Fréchet metrics.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.nn import functional as F

from world_model.eval.crops import NUM_CROP_STATS
from world_model.scene import CATEGORIES, NAMED_COLORS, TIMES_OF_DAY, WEATHERS

BACKGROUND = "background"
CROP_CLASSES = (*CATEGORIES, BACKGROUND)
COLOR_CLASSES = tuple(NAMED_COLORS)


@dataclass(frozen=True)
class JudgeNetConfig:
    """Sizes of the two judge networks (every default visible)."""

    crop_size: int = 32  # crops are resized to crop_size x crop_size
    crop_channels: tuple[int, ...] = (32, 64, 96)  # one stride-2 stage per entry
    crop_hidden: int = 128
    embed_dim: int = 64
    scene_channels: tuple[int, ...] = (16, 32, 64, 64)  # one stride-2 stage per entry
    scene_hidden: int = 64

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> JudgeNetConfig:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def _trunk(channels: tuple[int, ...]) -> nn.Sequential:
    """Stages of (3x3 conv stride 2, ReLU, 3x3 conv, ReLU): each halves the resolution."""
    layers: list[nn.Module] = []
    c_in = 3
    for c in channels:
        layers += [nn.Conv2d(c_in, c, 3, stride=2, padding=1), nn.ReLU(), nn.Conv2d(c, c, 3, padding=1), nn.ReLU()]
        c_in = c
    return nn.Sequential(*layers)


class CropNet(nn.Module):
    """Object crop -> category / colour / clarity / embedding."""

    def __init__(self, config: JudgeNetConfig) -> None:
        super().__init__()
        self.config = config
        self.trunk = _trunk(config.crop_channels)
        feat = 2 * config.crop_channels[-1] + NUM_CROP_STATS  # mean + max pooling, crop statistics
        self.mlp = nn.Sequential(nn.Linear(feat, config.crop_hidden), nn.ReLU())
        self.category = nn.Linear(config.crop_hidden, len(CROP_CLASSES))
        self.color = nn.Linear(config.crop_hidden, len(COLOR_CLASSES))
        self.clarity = nn.Linear(config.crop_hidden, 1)
        self.embed = nn.Linear(config.crop_hidden, config.embed_dim)
        # same_logit = scale * cos + bias, learned (initialized to a usable range).
        self.pair_scale = nn.Parameter(torch.tensor(10.0))
        self.pair_bias = nn.Parameter(torch.tensor(-5.0))

    def forward(self, crops: torch.Tensor, stats: torch.Tensor) -> dict[str, torch.Tensor]:
        """crops (N, 3, S, S) in [0, 1], stats (N, NUM_CROP_STATS) from ``crop_statistics`` ->
        category (N, 12), color (N, 17), clarity (N,), embedding (N, E) unit-norm."""
        f = self.trunk(crops * 2.0 - 1.0)
        f = torch.cat([f.mean(dim=(2, 3)), f.amax(dim=(2, 3)), stats], dim=1)
        h = self.mlp(f)
        return {
            "category": self.category(h),
            "color": self.color(h),
            "clarity": self.clarity(h)[:, 0],
            "embedding": F.normalize(self.embed(h), dim=1),
        }

    def same_logit(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Logit that embeddings a (N, E) and b (N, E) show the same object -> (N,)."""
        return self.pair_scale * (a * b).sum(dim=1) + self.pair_bias


class SceneNet(nn.Module):
    """Multi-view frame -> weather / time-of-day logits and pooled judge features."""

    def __init__(self, config: JudgeNetConfig) -> None:
        super().__init__()
        self.config = config
        self.trunk = _trunk(config.scene_channels)
        self.mlp = nn.Sequential(nn.Linear(2 * config.scene_channels[-1], config.scene_hidden), nn.ReLU())
        self.weather = nn.Linear(config.scene_hidden, len(WEATHERS))
        self.time_of_day = nn.Linear(config.scene_hidden, len(TIMES_OF_DAY))

    def features(self, views: torch.Tensor) -> torch.Tensor:
        """views (N, V, 3, H, W) in [0, 1] -> (N, scene_hidden) features averaged over views."""
        n, v = views.shape[:2]
        f = self.trunk(views.flatten(0, 1) * 2.0 - 1.0)
        f = torch.cat([f.mean(dim=(2, 3)), f.amax(dim=(2, 3))], dim=1)
        return self.mlp(f).view(n, v, -1).mean(dim=1)

    def forward(self, views: torch.Tensor) -> dict[str, torch.Tensor]:
        """views (N, V, 3, H, W) -> weather (N, 5), time_of_day (N, 3), features (N, F)."""
        h = self.features(views)
        return {"weather": self.weather(h), "time_of_day": self.time_of_day(h), "features": h}
