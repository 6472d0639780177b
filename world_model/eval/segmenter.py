"""The segmenter: which scene class every pixel of one camera view shows, from the pixels alone.

It scores generated camera frames against the ground truth's label maps (:mod:`world_model.eval.scene_iou`):
a frame that lost its road or its vehicles scores low however good its PSNR. The classes
(:data:`SCENE_CLASSES`) merge the simulator's label classes (:mod:`world_model.raster.classes`) into
what the metric asks about; :func:`scene_classes` maps a label map onto them.

:class:`SegNet` is a small U-Net (plain PyTorch) at the camera's own resolution; :class:`Segmenter`
wraps it for uint8 frames and persistence. The shipped weights (``world_model/assets/segmenter``,
trained by ``python -m world_model.eval.train_segmenter``) load with :func:`load_default_segmenter`;
``segmenter.json`` is sealed (hash of the weights and of its own body) so an edited file is refused.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn
from torch.nn import functional as F

from world_model.data.clips import sha256_file, write_json_atomic
from world_model.raster.classes import LABEL_CLASSES, MARKING, OFFROAD, OTHER_OBJECT, ROAD, SKY, VEHICLE, VULNERABLE

SCENE_CLASSES: tuple[str, ...] = (
    "background",  # sky and off-road ground
    "road",
    "marking",  # lane markings and road edges
    "vehicle",
    "vulnerable",  # pedestrians and cyclists
    "other_object",  # cones, barriers
)
NUM_SCENE_CLASSES = len(SCENE_CLASSES)

_LABEL_TO_SCENE = {SKY: 0, OFFROAD: 0, ROAD: 1, MARKING: 2, VEHICLE: 3, VULNERABLE: 4, OTHER_OBJECT: 5}
assert sorted(_LABEL_TO_SCENE) == list(range(len(LABEL_CLASSES))), "every label class needs a scene class"
_LUT = np.array([_LABEL_TO_SCENE[c] for c in range(len(LABEL_CLASSES))], dtype=np.uint8)

DEFAULT_SEGMENTER_DIR = Path(__file__).resolve().parent.parent / "assets" / "segmenter"
WEIGHTS_FILE = "segmenter.safetensors"
CONFIG_FILE = "segmenter.json"


def scene_classes(label_map: np.ndarray) -> np.ndarray:
    """Label map of :data:`~world_model.raster.classes.LABEL_CLASSES` ids (any shape, integer) -> the
    same shape of :data:`SCENE_CLASSES` ids, uint8."""
    labels = np.asarray(label_map)
    if not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"label map must hold integer class ids, got dtype {labels.dtype}")
    if labels.size and (labels.min() < 0 or labels.max() >= len(LABEL_CLASSES)):
        raise ValueError(f"label map holds ids {labels.min()}..{labels.max()} outside [0, {len(LABEL_CLASSES)})")
    return _LUT[labels]


@dataclass(frozen=True)
class SegmenterConfig:
    """Sizes of :class:`SegNet` (every default visible)."""

    channels: tuple[int, ...] = (32, 64, 96, 128)  # one stride-2 encoder stage per entry
    head_channels: int = 16  # the full-resolution refinement before the class logits

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> SegmenterConfig:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def _conv(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU())


class SegNet(nn.Module):
    """A small U-Net: stride-2 encoder stages, bilinear upsampling with skip connections back to
    half resolution, and a full-resolution head that sees the image again (thin lane markings are
    one or two pixels wide). The input gets a row-coordinate channel: the horizon's height is a
    strong cue for sky versus ground."""

    def __init__(self, config: SegmenterConfig = SegmenterConfig()) -> None:
        super().__init__()
        self.config = config
        ch = config.channels
        self.down = nn.ModuleList()
        c_in = 4  # RGB + row coordinate
        for c in ch:
            self.down.append(nn.Sequential(_conv(c_in, c, stride=2), _conv(c, c)))
            c_in = c
        self.up = nn.ModuleList(_conv(ch[i + 1] + ch[i], ch[i]) for i in reversed(range(len(ch) - 1)))
        self.head = nn.Sequential(
            _conv(ch[0] + 4, config.head_channels), nn.Conv2d(config.head_channels, NUM_SCENE_CLASSES, 1)
        )

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (N, 3, H, W) in [0, 1], H and W divisible by 2 ** len(channels) -> logits
        (N, NUM_SCENE_CLASSES, H, W)."""
        n, _, h, w = images.shape
        step = 2 ** len(self.config.channels)
        if h % step or w % step:
            raise ValueError(f"image size {h}x{w} must be divisible by {step} (2 ** number of encoder stages)")
        rows = torch.linspace(-1.0, 1.0, h, dtype=images.dtype, device=images.device)
        x = torch.cat([images * 2.0 - 1.0, rows.view(1, 1, h, 1).expand(n, 1, h, w)], dim=1)
        skips = []
        f = x
        for stage in self.down:
            f = stage(f)
            skips.append(f)
        for i, block in enumerate(self.up):
            skip = skips[-2 - i]
            f = block(torch.cat([F.interpolate(f, size=skip.shape[2:], mode="bilinear", align_corners=False), skip], 1))
        f = F.interpolate(f, size=(h, w), mode="bilinear", align_corners=False)
        return self.head(torch.cat([f, x], dim=1))


class Segmenter:
    """:class:`SegNet` on uint8 frames, in batches, with its training record (``info``)."""

    def __init__(self, net: SegNet, batch_size: int = 96, info: dict | None = None) -> None:
        self.net = net.eval()
        self.batch_size = batch_size
        self.info = info or {}

    @torch.no_grad()
    def predict(self, images: np.ndarray) -> np.ndarray:
        """uint8 images (..., H, W, 3) -> (..., H, W) uint8 :data:`SCENE_CLASSES` ids."""
        if images.dtype != np.uint8 or images.ndim < 3 or images.shape[-1] != 3:
            raise ValueError(f"images must be uint8 (..., H, W, 3), got {images.dtype} {images.shape}")
        flat = images.reshape(-1, *images.shape[-3:])
        out = np.empty(flat.shape[:3], dtype=np.uint8)
        for i in range(0, len(flat), self.batch_size):
            x = torch.from_numpy(np.array(flat[i : i + self.batch_size])).permute(0, 3, 1, 2).float() / 255
            out[i : i + len(x)] = self.net(x).argmax(1).to(torch.uint8).numpy()
        return out.reshape(images.shape[:-1])

    def save(self, out_dir: str | Path) -> Path:
        """Write ``segmenter.safetensors`` and the sealed ``segmenter.json`` (config, classes, info)."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        save_file({k: v.contiguous() for k, v in self.net.state_dict().items()}, str(out / WEIGHTS_FILE))
        meta = {
            "net": self.net.config.to_dict(),
            "scene_classes": list(SCENE_CLASSES),
            "weights_sha256": sha256_file(out / WEIGHTS_FILE),
            "info": self.info,
        }
        write_json_atomic(out / CONFIG_FILE, {**meta, "digest": _digest(meta)})
        return out


def _digest(meta: dict) -> str:
    return hashlib.sha256(json.dumps(meta, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def load_segmenter(path: str | Path) -> Segmenter:
    """Load a :class:`Segmenter` saved by :meth:`Segmenter.save` (a directory); refuses weights or a
    JSON that changed after saving, and classes that differ from :data:`SCENE_CLASSES`."""
    root = Path(path)
    weights, config = root / WEIGHTS_FILE, root / CONFIG_FILE
    if not weights.exists() or not config.exists():
        raise FileNotFoundError(
            f"{root} holds no segmenter ({WEIGHTS_FILE} + {CONFIG_FILE}); train one with "
            f"`python -m world_model.eval.train_segmenter --data DIR --heldout DIR --out {root}`"
        )
    meta = json.loads(config.read_text())
    body = {k: v for k, v in meta.items() if k != "digest"}
    if meta.get("digest") != _digest(body):
        raise ValueError(f"{config}: its digest does not match its contents (edited after saving?)")
    if sha256_file(weights) != meta["weights_sha256"]:
        raise ValueError(f"{weights}: sha256 differs from weights_sha256 in {CONFIG_FILE} (replaced or damaged)")
    if tuple(meta["scene_classes"]) != SCENE_CLASSES:
        raise ValueError(f"{root}: segmenter predicts {meta['scene_classes']}, this code has {list(SCENE_CLASSES)}")
    net = SegNet(SegmenterConfig.from_dict(meta["net"]))
    net.load_state_dict(load_file(str(weights)))
    return Segmenter(net, info=meta.get("info", {}))


def load_default_segmenter() -> Segmenter:
    """The segmenter shipped with the package (``world_model/assets/segmenter``)."""
    return load_segmenter(DEFAULT_SEGMENTER_DIR)
