"""The judge (paper §8): yes/no questions about generated frames, answered by a backend.

:class:`JudgeBackend` is the question interface; a VLM backend implements the same methods by
prompting ("Is it rainy in this image?", "Is the object in the box a bus?", ...). The default
backend, :class:`CnnJudge`, answers with the small networks of :mod:`world_model.eval.nets`
trained on procedural ground truth (``python -m world_model.eval.train_judge``), comparing their
probabilities to thresholds calibrated on held-out clips. :func:`load_default_judge` loads the
shipped weights from ``world_model/assets/judge``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from world_model.eval.crops import CropConfig, crop_statistics, normalize_crops
from world_model.eval.nets import COLOR_CLASSES, CROP_CLASSES, CropNet, JudgeNetConfig, SceneNet
from world_model.eval.text import parse_description
from world_model.scene import CATEGORIES, TIMES_OF_DAY, WEATHERS

DEFAULT_JUDGE_DIR = Path(__file__).resolve().parent.parent / "assets" / "judge"
WEIGHTS_FILE = "judge.safetensors"
CONFIG_FILE = "judge.json"


@runtime_checkable
class JudgeBackend(Protocol):
    """Batched yes/no answers. Frames are uint8 (N, V, H, W, 3); crops are uint8 (h, w, 3) each.
    Every method returns a bool array (N,)."""

    def is_weather(self, frames: np.ndarray, weathers: Sequence[str]) -> np.ndarray:
        """Is it <weather> in this multi-view frame?"""
        ...

    def is_time_of_day(self, frames: np.ndarray, times: Sequence[str]) -> np.ndarray:
        """Is it <time of day> in this multi-view frame?"""
        ...

    def is_category(self, crops: Sequence[np.ndarray], categories: Sequence[str]) -> np.ndarray:
        """Is the object in this crop a <category>? (existence)"""
        ...

    def is_clear(self, crops: Sequence[np.ndarray]) -> np.ndarray:
        """Is the object in this crop clearly discernible? (clarity)"""
        ...

    def same_object(self, crops_a: Sequence[np.ndarray], crops_b: Sequence[np.ndarray]) -> np.ndarray:
        """Does the crop show the same object as the reference crop? (visual fidelity)"""
        ...

    def consistent(self, crops_a: Sequence[np.ndarray], crops_b: Sequence[np.ndarray]) -> np.ndarray:
        """Are these crops of one instant, from two views, the same object? (cross-view consistency)"""
        ...

    def understands(self, description: str) -> bool:
        """Whether this backend can judge ``description`` at all (otherwise it is not asked)."""
        ...

    def matches_description(self, crops: Sequence[np.ndarray], descriptions: Sequence[str]) -> np.ndarray:
        """Does the object in this crop match the description? (textual fidelity)"""
        ...


@dataclass(frozen=True)
class JudgeThresholds:
    """Probabilities at or above which the CNN judge answers yes (calibrated on held-out clips)."""

    weather: float = 0.5
    time_of_day: float = 0.5
    category: float = 0.5
    color: float = 0.5
    clarity: float = 0.5
    visual_fidelity: float = 0.5
    consistency: float = 0.5


def _index(names: Sequence[str], vocab: Sequence[str], what: str) -> np.ndarray:
    lookup = {v: i for i, v in enumerate(vocab)}
    bad = sorted({n for n in names if n not in lookup})
    if bad:
        raise ValueError(f"unknown {what} {bad}; choose from {tuple(vocab)}")
    return np.array([lookup[n] for n in names], dtype=np.int64)


class CnnJudge:
    """The default :class:`JudgeBackend`: a crop network and a scene network plus thresholds."""

    def __init__(
        self,
        crop_net: CropNet,
        scene_net: SceneNet,
        thresholds: JudgeThresholds = JudgeThresholds(),
        crop_config: CropConfig | None = None,
        batch_size: int = 256,
        info: dict | None = None,
    ) -> None:
        self.crop_net = crop_net.eval()
        self.scene_net = scene_net.eval()
        self.thresholds = thresholds
        self.crop_config = crop_config or CropConfig()
        self.batch_size = batch_size
        self.info = info or {}

    # -- raw probabilities (also used for calibration) ---------------------------------------

    @torch.no_grad()
    def crop_outputs(self, crops: Sequence[np.ndarray]) -> dict[str, np.ndarray]:
        """Per crop: category (N, 12) and colour (N, 17) probabilities, clarity (N,) probability,
        embedding (N, E)."""
        size = self.crop_net.config.crop_size
        outs: dict[str, list[np.ndarray]] = {"category": [], "color": [], "clarity": [], "embedding": []}
        for i in range(0, len(crops), self.batch_size):
            chunk = crops[i : i + self.batch_size]
            o = self.crop_net(torch.from_numpy(normalize_crops(chunk, size)), torch.from_numpy(crop_statistics(chunk)))
            outs["category"].append(o["category"].softmax(1).numpy())
            outs["color"].append(o["color"].softmax(1).numpy())
            outs["clarity"].append(o["clarity"].sigmoid().numpy())
            outs["embedding"].append(o["embedding"].numpy())
        dims = {"category": (len(CROP_CLASSES),), "color": (len(COLOR_CLASSES),), "clarity": ()}
        dims["embedding"] = (self.crop_net.config.embed_dim,)
        return {k: np.concatenate(v) if v else np.zeros((0, *dims[k]), np.float32) for k, v in outs.items()}

    @torch.no_grad()
    def pair_probs(self, emb_a: np.ndarray, emb_b: np.ndarray) -> np.ndarray:
        """Probability that embeddings (N, E) and (N, E) show the same object -> (N,)."""
        return self.crop_net.same_logit(torch.from_numpy(emb_a), torch.from_numpy(emb_b)).sigmoid().numpy()

    @torch.no_grad()
    def scene_outputs(self, frames: np.ndarray) -> dict[str, np.ndarray]:
        """frames (N, V, H, W, 3) uint8 -> weather (N, 5) and time_of_day (N, 3) probabilities,
        features (N, F)."""
        if frames.dtype != np.uint8 or frames.ndim != 5 or frames.shape[-1] != 3:
            raise ValueError(f"frames must be uint8 (N, V, H, W, 3), got {frames.dtype} {frames.shape}")
        outs: dict[str, list[np.ndarray]] = {"weather": [], "time_of_day": [], "features": []}
        step = max(1, self.batch_size // (4 * frames.shape[1]))
        for i in range(0, len(frames), step):
            x = torch.from_numpy(np.array(frames[i : i + step])).permute(0, 1, 4, 2, 3).float() / 255.0
            o = self.scene_net(x)
            outs["weather"].append(o["weather"].softmax(1).numpy())
            outs["time_of_day"].append(o["time_of_day"].softmax(1).numpy())
            outs["features"].append(o["features"].numpy())
        return {k: np.concatenate(v) for k, v in outs.items()}

    def frame_features(self, frames: np.ndarray) -> np.ndarray:
        """Judge features of frames (N, V, H, W, 3) uint8 -> (N, F) float64 (Fréchet metrics)."""
        return self.scene_outputs(frames)["features"].astype(np.float64)

    # -- the questions -----------------------------------------------------------------------

    def is_weather(self, frames: np.ndarray, weathers: Sequence[str]) -> np.ndarray:
        p = self.scene_outputs(frames)["weather"]
        return p[np.arange(len(p)), _index(weathers, WEATHERS, "weather")] >= self.thresholds.weather

    def is_time_of_day(self, frames: np.ndarray, times: Sequence[str]) -> np.ndarray:
        p = self.scene_outputs(frames)["time_of_day"]
        return p[np.arange(len(p)), _index(times, TIMES_OF_DAY, "time of day")] >= self.thresholds.time_of_day

    def is_category(self, crops: Sequence[np.ndarray], categories: Sequence[str]) -> np.ndarray:
        idx = _index(categories, CATEGORIES, "category")
        p = self.crop_outputs(crops)["category"]
        return p[np.arange(len(p)), idx] >= self.thresholds.category

    def is_clear(self, crops: Sequence[np.ndarray]) -> np.ndarray:
        return self.crop_outputs(crops)["clarity"] >= self.thresholds.clarity

    def same_object(self, crops_a: Sequence[np.ndarray], crops_b: Sequence[np.ndarray]) -> np.ndarray:
        if len(crops_a) != len(crops_b):
            raise ValueError(f"same_object needs pairs: got {len(crops_a)} and {len(crops_b)} crops")
        ea, eb = self.crop_outputs(crops_a)["embedding"], self.crop_outputs(crops_b)["embedding"]
        return self.pair_probs(ea, eb) >= self.thresholds.visual_fidelity

    def consistent(self, crops_a: Sequence[np.ndarray], crops_b: Sequence[np.ndarray]) -> np.ndarray:
        """Cross-view variant of :meth:`same_object` with its own calibrated threshold."""
        ea, eb = self.crop_outputs(crops_a)["embedding"], self.crop_outputs(crops_b)["embedding"]
        return self.pair_probs(ea, eb) >= self.thresholds.consistency

    def understands(self, description: str) -> bool:
        return not parse_description(description).empty

    def matches_description(self, crops: Sequence[np.ndarray], descriptions: Sequence[str]) -> np.ndarray:
        """Yes when every attribute the description names (category word, colour word) is
        recognized in the crop by the category / colour heads. Raises on a description naming
        neither (check :meth:`understands` first)."""
        if len(crops) != len(descriptions):
            raise ValueError(f"got {len(crops)} crops for {len(descriptions)} descriptions")
        out = self.crop_outputs(crops)
        yes = np.ones(len(crops), dtype=bool)
        for i, text in enumerate(descriptions):
            parsed = parse_description(text)
            if parsed.empty:
                raise ValueError(f"cannot judge description {text!r}: it names no known colour or category")
            if parsed.category is not None:
                yes[i] &= out["category"][i, CROP_CLASSES.index(parsed.category)] >= self.thresholds.category
            if parsed.color is not None:
                yes[i] &= out["color"][i, COLOR_CLASSES.index(parsed.color)] >= self.thresholds.color
        return yes

    # -- persistence ---------------------------------------------------------------------------

    def save(self, out_dir: str | Path) -> Path:
        """Write ``judge.safetensors`` and ``judge.json`` (configs, thresholds, info) to ``out_dir``."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        tensors = {f"crop.{k}": v.contiguous() for k, v in self.crop_net.state_dict().items()}
        tensors.update({f"scene.{k}": v.contiguous() for k, v in self.scene_net.state_dict().items()})
        save_file(tensors, str(out / WEIGHTS_FILE))
        meta = {
            "net": self.crop_net.config.to_dict(),
            "crop": asdict(self.crop_config),
            "thresholds": asdict(self.thresholds),
            "crop_classes": list(CROP_CLASSES),
            "color_classes": list(COLOR_CLASSES),
            "weathers": list(WEATHERS),
            "times_of_day": list(TIMES_OF_DAY),
            "info": self.info,
        }
        (out / CONFIG_FILE).write_text(json.dumps(meta, indent=1))
        return out


def load_judge(path: str | Path) -> CnnJudge:
    """Load a :class:`CnnJudge` saved by :meth:`CnnJudge.save` (a directory)."""
    root = Path(path)
    if not (root / WEIGHTS_FILE).exists() or not (root / CONFIG_FILE).exists():
        raise FileNotFoundError(
            f"{root} holds no judge ({WEIGHTS_FILE} + {CONFIG_FILE}); train one with "
            f"`python -m world_model.eval.train_judge --data DIR --out {root}`"
        )
    meta = json.loads((root / CONFIG_FILE).read_text())
    vocab = {"crop_classes": CROP_CLASSES, "color_classes": COLOR_CLASSES, "weathers": WEATHERS}
    vocab["times_of_day"] = TIMES_OF_DAY
    for key, current in vocab.items():
        if tuple(meta[key]) != tuple(current):
            raise ValueError(f"{root}: judge was trained for {key} {meta[key]}, this code has {list(current)}")
    cfg = JudgeNetConfig.from_dict(meta["net"])
    crop_net, scene_net = CropNet(cfg), SceneNet(cfg)
    tensors = load_file(str(root / WEIGHTS_FILE))
    crop_net.load_state_dict({k[5:]: v for k, v in tensors.items() if k.startswith("crop.")})
    scene_net.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("scene.")})
    return CnnJudge(
        crop_net,
        scene_net,
        thresholds=JudgeThresholds(**meta["thresholds"]),
        crop_config=CropConfig(**meta["crop"]),
        info=meta.get("info", {}),
    )


def load_default_judge() -> CnnJudge:
    """The judge shipped with the package (``world_model/assets/judge``)."""
    return load_judge(DEFAULT_JUDGE_DIR)
