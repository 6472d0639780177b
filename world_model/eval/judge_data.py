"""Ground-truth material for training and measuring the judge, collected from recorded clips.

From each clip: object crops (the judge's own crop filter, :mod:`world_model.eval.crops`) every
``crop_stride`` frames, background crops that overlap no object, the clip's reference crops
(``clip.crops``), and multi-view frames every ``scene_stride`` frames with their weather and time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from world_model.data import list_clips, read_clip
from world_model.eval.corrupt import add_noise, blur, pixelate
from world_model.eval.crops import CropConfig, extract_crops
from world_model.eval.nets import BACKGROUND, COLOR_CLASSES, CROP_CLASSES
from world_model.scene import TIMES_OF_DAY, WEATHERS
from world_model.sim import ProceduralSimulator


@dataclass(frozen=True)
class CollectConfig:
    """How densely clips are sampled."""

    crop_stride: int = 5  # frames between object-crop samples
    scene_stride: int = 20  # frames between multi-view frame samples
    background_per_frame: int = 1  # background crops per sampled frame (in a random view)
    background_tries: int = 20  # random boxes tried per background crop
    background_max_side_fraction: float = 0.6  # of the image height
    max_clips: int | None = None  # first N clips only (tests, quick runs)
    seed: int = 0
    crop: CropConfig = field(default_factory=CropConfig)


@dataclass(frozen=True)
class DegradeConfig:
    """One of blur / noise / pixelation at the image's native resolution, its strength drawn from
    the kind's range. The defaults make the clarity head's negatives."""

    blur_sigma: tuple[float, float] = (1.0, 2.5)  # pixels
    noise_std: tuple[float, float] = (15.0, 40.0)  # 0-255 scale
    pixelate: tuple[int, int] = (2, 4)  # block size range, inclusive


# What a generated view may carry without its weather or time of day changing: an autoencoder's
# reconstruction is about a pixel softer than the recording, with faint noise and 2x2 blockiness.
# The scene network trains on views jittered this way, and the judge's benchmark asks it about
# held-out views under fixed ones of the same kinds.
VIEW_JITTER = DegradeConfig(blur_sigma=(0.3, 1.2), noise_std=(1.0, 6.0), pixelate=(2, 2))
MILD_DEGRADATIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "blur 0.7 px": lambda images: blur(images, 0.7),
    "noise 4/255": lambda images: add_noise(images, 4.0, np.random.default_rng(0)),
    "pixelate 2": lambda images: pixelate(images, 2),
}


def degrade(crop: np.ndarray, rng: np.random.Generator, config: DegradeConfig = DegradeConfig()) -> np.ndarray:
    """A blurred, noised or pixelated copy of one uint8 (h, w, 3) image."""
    kind = int(rng.integers(3))
    if kind == 0:
        return blur(crop, float(rng.uniform(*config.blur_sigma)))
    if kind == 1:
        return add_noise(crop, float(rng.uniform(*config.noise_std)), rng)
    return pixelate(crop, int(rng.integers(config.pixelate[0], config.pixelate[1] + 1)))


@dataclass(frozen=True)
class CropLabels:
    """One crop's labels, as :class:`JudgeData` keeps them (its docstring)."""

    category: int
    color: int
    track: int
    frame: int
    view: int
    clip: int
    reference: bool
    description: str


CROP_LABELS = tuple(f.name for f in fields(CropLabels))  # JudgeData's per-crop label lists


@dataclass
class JudgeData:
    """Crops (raw, variable size) with labels, and multi-view frames with scene labels.

    Per crop: ``category`` indexes ``CROP_CLASSES`` (background last), ``color`` indexes
    ``COLOR_CLASSES`` or -1 (not a named colour / background), ``track`` is a global track id or -1
    (background), ``frame`` a global frame id (-1 for reference crops), ``view`` -1 for reference
    crops. ``clip`` indexes ``clip_names``.
    """

    crops: list[np.ndarray] = field(default_factory=list)
    category: list[int] = field(default_factory=list)
    color: list[int] = field(default_factory=list)
    track: list[int] = field(default_factory=list)
    frame: list[int] = field(default_factory=list)
    view: list[int] = field(default_factory=list)
    clip: list[int] = field(default_factory=list)
    reference: list[bool] = field(default_factory=list)
    description: list[str] = field(default_factory=list)
    scene_frames: list[np.ndarray] = field(default_factory=list)  # (V, H, W, 3) each
    weather: list[int] = field(default_factory=list)
    time_of_day: list[int] = field(default_factory=list)
    scene_clip: list[int] = field(default_factory=list)
    clip_names: list[str] = field(default_factory=list)

    def add_crop(self, image: np.ndarray, labels: CropLabels) -> None:
        self.crops.append(image)
        for name in CROP_LABELS:
            getattr(self, name).append(getattr(labels, name))

    def labels(self, i: int) -> CropLabels:
        """The labels of crop ``i``."""
        return CropLabels(**{name: getattr(self, name)[i] for name in CROP_LABELS})

    def arrays(self) -> dict[str, np.ndarray]:
        """The per-crop label lists as int / bool arrays (N,)."""
        keys = ("category", "color", "track", "frame", "view", "clip")
        out = {k: np.asarray(getattr(self, k), dtype=np.int64) for k in keys}
        out["reference"] = np.asarray(self.reference, dtype=bool)
        return out


def _overlaps(box: tuple[int, int, int, int], others: list[tuple[int, int, int, int]]) -> bool:
    x0, y0, x1, y1 = box
    return any(x0 < b[2] and b[0] < x1 and y0 < b[3] and b[1] < y1 for b in others)


def collect(
    root: str | Path, config: CollectConfig = CollectConfig(), clip_names: list[str] | None = None
) -> JudgeData:
    """Collect :class:`JudgeData` from the clips of the dataset at ``root`` (all, or ``clip_names``)."""
    names = list_clips(root) if clip_names is None else clip_names
    if config.max_clips is not None:
        names = names[: config.max_clips]
    if not names:
        raise ValueError(f"{root}: no clips to collect judge data from")
    sim = ProceduralSimulator()
    data = JudgeData(clip_names=list(names))
    track_ids: dict[tuple[int, str], int] = {}
    frame_id = 0
    for ci, name in enumerate(names):
        clip = read_clip(root, name)
        rng = np.random.default_rng([config.seed, ci])
        info: dict[str, tuple[int, int, str]] = {}
        h, w = clip.frames[0].rig.resolution
        min_side = config.crop.threshold(h)
        max_side = max(min_side + 1, config.background_max_side_fraction * h)
        for fi in range(0, clip.num_frames, config.crop_stride):
            frame, cams = clip.frames[fi], np.asarray(clip.cameras[fi])
            for c in extract_crops(frame, cams, sim, config.crop):
                tid = track_ids.setdefault((ci, c.track_id), len(track_ids))
                color = COLOR_CLASSES.index(c.color_name) if c.color_name in COLOR_CLASSES else -1
                cat = CROP_CLASSES.index(c.category)
                info[c.track_id] = (cat, color, c.description)
                data.add_crop(c.image, CropLabels(cat, color, tid, frame_id, c.view, ci, False, c.description))
            for _ in range(config.background_per_frame):
                view = int(rng.integers(cams.shape[0]))
                boxes = list(sim.object_boxes_2d(frame, view).values())
                for _try in range(config.background_tries):
                    bh = int(rng.uniform(min_side, max_side))
                    bw = int(np.clip(bh * np.exp(rng.uniform(-0.5, 1.0)), min_side, w))
                    x0, y0 = int(rng.integers(0, w - bw + 1)), int(rng.integers(0, h - bh + 1))
                    box = (x0, y0, x0 + bw, y0 + bh)
                    if not _overlaps(box, boxes):
                        crop = np.ascontiguousarray(cams[view, y0 : y0 + bh, x0 : x0 + bw])
                        labels = CropLabels(CROP_CLASSES.index(BACKGROUND), -1, -1, frame_id, view, ci, False, "")
                        data.add_crop(crop, labels)
                        break
            frame_id += 1
        for tid_name, ref in sorted(clip.crops.items()):
            if tid_name in info and min(ref.shape[:2]) > 0:
                cat, color, desc = info[tid_name]
                data.add_crop(ref, CropLabels(cat, color, track_ids[(ci, tid_name)], -1, -1, ci, True, desc))
        prompt = clip.frames[0].prompt
        for fi in range(0, clip.num_frames, config.scene_stride):
            data.scene_frames.append(np.asarray(clip.cameras[fi]).copy())
            data.weather.append(WEATHERS.index(prompt.weather))
            data.time_of_day.append(TIMES_OF_DAY.index(prompt.time_of_day))
            data.scene_clip.append(ci)
    return data
