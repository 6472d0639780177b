"""SceneFrames -> numeric condition arrays -> batched :class:`Conditions` tensors (§3.2).

The conversion is pure (no learned weights): text and crops are turned into embeddings by
encoders that cache by content, everything else is geometry. The learned part (Fourier
embeddings, MLPs, null features) lives in :mod:`world_model.model.tokens`.

Shapes (T frames, Vc cameras, V = Vc + 1 views, O = ``control.max_objects``, L = ``text.max_tokens``,
Dt text width, Di image-feature width):

=================  ====================  ===============================================
camera             (Vc, 7, 3)            ``[K; R; t^T]``, K rows 0/1 divided by width/height
ego                (T, 4, 3)             ``[R; t^T]`` relative to ``first_ego``
bev                (T, h, w, c) uint8    the BEV raster, {0, 1}
obj_corners        (T, O, 8, 3)          box corners in the current LiDAR frame
obj_category       (T, O, Dt)            pooled embedding of the category name
obj_text           (T, O, Dt)            pooled embedding of the text description
obj_image          (T, O, Di)            image-description feature of the reference crop
obj_mask           (T, O) bool           real object (False = padding)
obj_has_text       (T, O) bool           a text description exists
obj_has_image      (T, O) bool           a reference crop exists
text, text_mask    (L, Dt), (L,) bool    prompt tokens, padding masked
view_adjacency     (V, V) bool           FoV overlap (self excluded); LiDAR overlaps all
layout             (T, V, Cl, h, w)      pixel-aligned layout at the latent resolution
                                         (:mod:`world_model.model.layout`); Cl =
                                         ``layout.channels``, 0 when disabled
labels             (T, Vc, 3, H, W)      each camera's label map at full resolution for the
                   uint8                 VAE decoder (``layout.decoder``): class ids
                                         (:data:`~world_model.raster.classes.LABEL_CLASSES`),
                                         the objects' paint, the ground's surface
                                         (:class:`~world_model.raster.maps.SceneRaster`);
                                         H = W = 0 without it. The DiTs do not read it.
lidar_nearness     (T, H, W) uint8       the range map the scene implies on the LiDAR view at
                                         full resolution, for the decoder
                                         (``layout.decoder``,
                                         :class:`~world_model.raster.maps.SceneRaster`);
                                         H = W = 0 without it. The DiTs do not read it.
range_nearness     (T, B, A) uint16      the same at the range map's resolution (B beams,
                                         A azimuth columns) in finer steps
                                         (``layout.RANGE_LEVELS``), for the VAE's range head
                                         (``layout.range_head``); B = A = 0 without it.
precipitation      (T, Vc, H, W) uint8   the alpha of the rain or snow in front of each
                                         camera (255 = opaque), blended over the decoded
                                         cameras (``SceneRaster.precipitation``); H = W
                                         = 0 without ``layout.decoder``. The DiTs do not
                                         read it.
precipitation_rgb  (T, 3) uint8          the colour it is blended in
=================  ====================  ===============================================

Objects beyond the cap are dropped farthest first (distance of the box centre from the LiDAR).
A missing text description falls back to "<colour> <category>" when the object has a colour
name, because colour is the fine-grained attribute scenarios set most often.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from world_model.model.config import ModelConfig
from world_model.model.imagedesc import ImageDescriptionEncoder, image_feature_dim
from world_model.model.layout import layout_sequence
from world_model.model.text import TextEncoder
from world_model.observation import ALL_SENSORS, SensorSelection
from world_model.raster.classes import MAP_PLANES
from world_model.scene import EgoState, SceneFrame, SceneObject, ScenePrompt
from world_model.sensors import CameraRig

if TYPE_CHECKING:  # the scene raster's renderer loads only where a map is drawn
    from world_model.raster.maps import SceneRaster


def view_adjacency(rig: CameraRig) -> np.ndarray:
    """(V, V) bool, V = cameras + LiDAR: which views see overlapping parts of the world.

    Two cameras overlap when the angle between their optical axes is less than the sum of their
    horizontal half-FoVs (the cameras sit within centimetres of each other, so the azimuth
    sectors decide). The 360-degree LiDAR overlaps every camera. A view is not its own neighbour
    (self-attention already covers it).
    """
    vc = rig.num_views
    adj = np.zeros((vc + 1, vc + 1), dtype=bool)
    for i, a in enumerate(rig.cameras):
        for j, b in enumerate(rig.cameras):
            if i != j:
                gap = abs(math.remainder(a.yaw - b.yaw, 2 * math.pi))
                adj[i, j] = gap < 0.5 * (a.hfov + b.hfov)
    adj[vc, :vc] = adj[:vc, vc] = True
    return adj


def camera_condition(rig: CameraRig) -> np.ndarray:
    """(Vc, 7, 3) ``[K; R; t^T]`` with K normalized by the image size."""
    mats = rig.condition_matrices().copy()
    for i, cam in enumerate(rig.cameras):
        mats[i, 0] /= cam.width
        mats[i, 1] /= cam.height
    return mats


# Rig object id -> (the rig, its camera condition, its view adjacency). By identity: a rig holds
# arrays (unhashable), and every frame of a rollout carries the same rig object. The entry keeps
# its rig alive, so the id cannot be reused by another object while it is cached.
_RIG_CONDITIONS: dict[int, tuple[CameraRig, np.ndarray, np.ndarray]] = {}
MAX_CACHED_RIGS = 64


def rig_conditions(rig: CameraRig) -> tuple[np.ndarray, np.ndarray]:
    """:func:`camera_condition` and :func:`view_adjacency` of ``rig``, computed once per rig object
    (a rollout's rig never changes) and read-only, since every rollout of the rig shares them."""
    hit = _RIG_CONDITIONS.get(id(rig))
    if hit is None or hit[0] is not rig:
        if len(_RIG_CONDITIONS) >= MAX_CACHED_RIGS:
            _RIG_CONDITIONS.clear()
        camera, adjacency = camera_condition(rig), view_adjacency(rig)
        camera.flags.writeable = adjacency.flags.writeable = False
        hit = _RIG_CONDITIONS[id(rig)] = (rig, camera, adjacency)
    return hit[1], hit[2]


def category_text(category: str) -> str:
    """The string a category's name is encoded as."""
    return category.replace("_", " ")


def condition_texts(frames: Sequence[SceneFrame]) -> tuple[set[str], set[str]]:
    """The strings :func:`build_condition_arrays` can encode for ``frames``: (token-level texts:
    the prompts, pooled texts: category names and object descriptions)."""
    prompts = {fr.prompt.full_text() for fr in frames}
    objects = [o for fr in frames for o in fr.objects]
    pooled = {category_text(o.category) for o in objects} | {object_text(o) for o in objects}
    return prompts, pooled - {""}


def object_text(obj: SceneObject) -> str:
    if obj.description.strip():
        return obj.description.strip()
    if obj.color_name:
        return f"{obj.color_name.replace('_', ' ')} {obj.category.replace('_', ' ')}"
    return ""


@dataclass
class ConditionArrays:
    """Numeric conditions of one sequence (numpy). See the module docstring for shapes."""

    camera: np.ndarray
    ego: np.ndarray
    bev: np.ndarray
    obj_corners: np.ndarray
    obj_category: np.ndarray
    obj_text: np.ndarray
    obj_image: np.ndarray
    obj_mask: np.ndarray
    obj_has_text: np.ndarray
    obj_has_image: np.ndarray
    text: np.ndarray
    text_mask: np.ndarray
    view_adjacency: np.ndarray
    layout: np.ndarray
    labels: np.ndarray
    lidar_nearness: np.ndarray
    range_nearness: np.ndarray
    precipitation: np.ndarray
    precipitation_rgb: np.ndarray

    TIME_FIELDS = (
        "ego",
        "bev",
        "obj_corners",
        "obj_category",
        "obj_text",
        "obj_image",
        "obj_mask",
        "obj_has_text",
        "obj_has_image",
        "layout",
        "labels",
        "lidar_nearness",
        "range_nearness",
        "precipitation",
        "precipitation_rgb",
    )

    @property
    def num_frames(self) -> int:
        return len(self.ego)

    @property
    def style(self) -> np.ndarray:
        """(Dt,) the scene's style for the label decoder (:func:`prompt_style`)."""
        return prompt_style(self.text, self.text_mask)

    def frames(self, start: int, stop: int) -> ConditionArrays:
        """Frames [start, stop). Ego poses stay relative to the sequence's first frame."""
        return replace(self, **{k: getattr(self, k)[start:stop] for k in self.TIME_FIELDS})


@dataclass(frozen=True)
class ConditionOptions:
    """What :func:`build_condition_arrays` reads beside a sequence's frames and map, each optional.

    ``image_encoder`` encodes the objects' reference crops; without one every object's image
    description counts as missing. ``crops`` by track id, each from frame ``crop_since[track]`` on
    (a track absent from it: every frame; :mod:`world_model.raster.crops`). ``first_ego``: the
    rollout's first ego state, which the ego condition is relative to (default: the first frame's).
    ``layout``: the frames' layout raster when computed already
    (:func:`world_model.model.layout.layout_sequence`, the training data's cache), else computed
    when the config enables it. ``raster`` draws the decoder's maps (default: a new
    :class:`~world_model.raster.maps.SceneRaster`; one kept across calls reuses its geometry), of the
    frames flagged in ``labeled`` (default: all) and the sensors in ``sensors`` (the cameras' label
    maps, the LiDAR view's nearness; a sensor that will not be decoded needs none)."""

    image_encoder: ImageDescriptionEncoder | None = None
    crops: Mapping[str, np.ndarray] | None = None
    crop_since: Mapping[str, int] | None = None
    first_ego: EgoState | None = None
    layout: np.ndarray | None = None
    raster: SceneRaster | None = None
    labeled: Sequence[bool] | None = None
    sensors: SensorSelection = ALL_SENSORS


def build_condition_arrays(
    frames: Sequence[SceneFrame],
    bev: np.ndarray,
    cfg: ModelConfig,
    text_encoder: TextEncoder,
    options: ConditionOptions | None = None,
) -> ConditionArrays:
    """Pure conversion of T frames and their BEV rasters (T, h, w, c) to condition arrays, with
    what ``options`` adds (crops, the rollout's first ego state, caches)."""
    if not frames:
        raise ValueError("build_condition_arrays needs at least one frame")
    opts = options or ConditionOptions()
    t = len(frames)
    bev = np.asarray(bev)
    expected = (t, *cfg.sensors.bev.shape)
    if bev.shape != expected:
        raise ValueError(f"bev must have shape {expected} (T, h, w, c) for this config, got {bev.shape}")
    rig = frames[0].rig
    if rig.num_views != cfg.sensors.num_cameras:
        raise ValueError(f"frames carry {rig.num_views} cameras but the model has {cfg.sensors.num_cameras}")
    raster = opts.raster or _new_raster(cfg)
    if raster.cfg is not cfg and raster.cfg != cfg:
        raise ValueError("options.raster draws the maps of another model config than cfg")
    first = opts.first_ego or frames[0].ego
    objects = _object_arrays(frames, cfg, text_encoder, opts)
    layout = _layout_arrays(frames, bev, cfg, opts.layout)
    unlabeled = [False] * t
    labels = raster.labels(frames, opts.labeled if opts.sensors.cameras else unlabeled)
    nearness = raster.nearness(frames, opts.labeled if opts.sensors.lidar else unlabeled)
    ranges = raster.range_nearness(frames, opts.labeled if opts.sensors.lidar else unlabeled)
    precipitation, precipitation_rgb = raster.precipitation(frames, opts.labeled if opts.sensors.cameras else unlabeled)
    tokens = prompt_tokens(frames[0].prompt, cfg, text_encoder)
    text = np.zeros((cfg.text.max_tokens, cfg.text.dim), np.float32)
    text[: len(tokens)] = tokens
    text_mask = np.arange(cfg.text.max_tokens) < len(tokens)
    camera, adjacency = rig_conditions(rig)
    return ConditionArrays(
        camera=camera,
        ego=np.stack([fr.ego_pose_condition(first) for fr in frames]).astype(np.float32),
        bev=bev.astype(np.uint8),
        **objects,
        text=text,
        text_mask=text_mask,
        view_adjacency=adjacency,
        layout=layout,
        labels=labels,
        lidar_nearness=nearness,
        range_nearness=ranges,
        precipitation=precipitation,
        precipitation_rgb=precipitation_rgb,
    )


def _new_raster(cfg: ModelConfig) -> SceneRaster:
    from world_model.raster.maps import SceneRaster

    return SceneRaster(cfg)


def _object_arrays(
    frames: Sequence[SceneFrame], cfg: ModelConfig, text_encoder: TextEncoder, opts: ConditionOptions
) -> dict[str, np.ndarray]:
    """The ``obj_*`` fields of ``frames``: the nearest ``control.max_objects`` objects of each frame."""
    t, o_max, dt, di = len(frames), cfg.control.max_objects, cfg.text.dim, image_feature_dim(cfg)
    image_encoder, crops, since = opts.image_encoder, opts.crops or {}, opts.crop_since or {}
    corners = np.zeros((t, o_max, 8, 3), np.float32)
    cat = np.zeros((t, o_max, dt), np.float32)
    txt = np.zeros((t, o_max, dt), np.float32)
    img = np.zeros((t, o_max, di), np.float32)
    mask = np.zeros((t, o_max), bool)
    has_txt = np.zeros((t, o_max), bool)
    has_img = np.zeros((t, o_max), bool)
    for f, fr in enumerate(frames):
        if not fr.objects:
            continue
        all_corners = fr.object_corners_lidar()
        dist = np.linalg.norm(all_corners.mean(axis=1)[:, :2], axis=1)
        keep = np.argsort(dist, kind="stable")[:o_max]
        objs = [fr.objects[i] for i in keep]
        n = len(objs)
        corners[f, :n] = all_corners[keep]
        mask[f, :n] = True
        cat[f, :n] = text_encoder.pooled([category_text(o.category) for o in objs])
        descs = [object_text(o) for o in objs]
        idx = [i for i, d in enumerate(descs) if d]
        if idx:
            txt[f, idx] = text_encoder.pooled([descs[i] for i in idx])
            has_txt[f, idx] = True
        if image_encoder is not None:
            ready = [since.get(o.track_id, fr.frame_index) <= fr.frame_index for o in objs]
            pairs = [
                (i, o.image if o.image is not None else crops.get(o.track_id) if ok else None)
                for i, (o, ok) in enumerate(zip(objs, ready, strict=True))
            ]
            pairs = [(i, c) for i, c in pairs if c is not None]
            if pairs:
                img[f, [i for i, _ in pairs]] = image_encoder.encode([c for _, c in pairs])
                has_img[f, [i for i, _ in pairs]] = True
    return {
        "obj_corners": corners,
        "obj_category": cat,
        "obj_text": txt,
        "obj_image": img,
        "obj_mask": mask,
        "obj_has_text": has_txt,
        "obj_has_image": has_img,
    }


def _layout_arrays(
    frames: Sequence[SceneFrame], bev: np.ndarray, cfg: ModelConfig, layout: np.ndarray | None
) -> np.ndarray:
    """The ``layout`` field: ``layout`` when given (checked), else computed when the config enables it."""
    t, (h, w) = len(frames), cfg.latent_hw
    if cfg.layout.enabled and layout is not None:
        expected = (t, cfg.sensors.num_views, cfg.layout.channels, h, w)
        if layout.shape != expected:
            raise ValueError(f"layout must have shape {expected} for this config, got {layout.shape}")
        return layout
    if cfg.layout.enabled:
        return layout_sequence(frames, bev, cfg.sensors.lidar, (h, w), cfg.layout.supersample)
    return np.zeros((t, cfg.sensors.num_views, 0, h, w), np.float32)


def prompt_tokens(prompt: ScenePrompt, cfg: ModelConfig, text_encoder: TextEncoder) -> np.ndarray:
    """(L, Dt) the prompt's token embeddings as the conditions hold them (at most ``text.max_tokens``)."""
    return text_encoder.tokens(prompt.full_text())[: cfg.text.max_tokens]


def style_of_prompt(prompt: ScenePrompt, cfg: ModelConfig, text_encoder: TextEncoder) -> np.ndarray:
    """(Dt,) :func:`prompt_style` of ``prompt`` as the conditions hold it (``ConditionArrays.style``)."""
    tokens = prompt_tokens(prompt, cfg, text_encoder)
    return prompt_style(tokens, np.ones(len(tokens), bool))


def prompt_style(text: np.ndarray | torch.Tensor, text_mask: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """The scene's style the label decoder reads (``layout.decoder``): the prompt's pooled
    embedding, the unit-length mean of its unmasked tokens (the sentence encoder's own pooling), so
    the weather and light the prompt names reach the decoder. text (..., L, Dt), text_mask (..., L)
    -> (..., Dt), numpy or torch as given."""
    if isinstance(text, torch.Tensor):
        mask = text_mask[..., None].to(text)
        mean = (text * mask).sum(-2) / mask.sum(-2).clamp_min(1.0)
        return mean / mean.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    mask = np.asarray(text_mask, np.float32)[..., None]
    mean = (np.asarray(text, np.float32) * mask).sum(-2) / np.maximum(mask.sum(-2), 1.0)
    return mean / np.maximum(np.linalg.norm(mean, axis=-1, keepdims=True), 1e-8)


@dataclass(frozen=True)
class FieldSpec:
    """Shape and dtype of one :class:`ConditionArrays` field."""

    shape: tuple[int, ...]
    dtype: np.dtype


def condition_field_specs(cfg: ModelConfig, num_frames: int) -> dict[str, FieldSpec]:
    """Every :class:`ConditionArrays` field's shape and dtype for ``num_frames`` frames under ``cfg``
    (the table of the module docstring): what :func:`build_condition_arrays` returns, known before
    any frame exists (e.g. to lay out shared memory for the arrays of many rollouts)."""
    t, o, dt, di = num_frames, cfg.control.max_objects, cfg.text.dim, image_feature_dim(cfg)
    vc, v = cfg.sensors.num_cameras, cfg.sensors.num_views
    h, w = cfg.latent_hw
    layout_channels = cfg.layout.channels if cfg.layout.enabled else 0
    label_hw = (cfg.sensors.height, cfg.sensors.width) if cfg.layout.decoder else (0, 0)
    nearness_hw = (cfg.sensors.height, cfg.sensors.width) if cfg.layout.decoder else (0, 0)
    range_hw = (cfg.sensors.lidar.beams, cfg.sensors.lidar.azimuth) if cfg.layout.range_head else (0, 0)
    f32, u8, u16, b = np.dtype(np.float32), np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(bool)
    return {
        "camera": FieldSpec((vc, 7, 3), f32),
        "ego": FieldSpec((t, 4, 3), f32),
        "bev": FieldSpec((t, *cfg.sensors.bev.shape), u8),
        "obj_corners": FieldSpec((t, o, 8, 3), f32),
        "obj_category": FieldSpec((t, o, dt), f32),
        "obj_text": FieldSpec((t, o, dt), f32),
        "obj_image": FieldSpec((t, o, di), f32),
        "obj_mask": FieldSpec((t, o), b),
        "obj_has_text": FieldSpec((t, o), b),
        "obj_has_image": FieldSpec((t, o), b),
        "text": FieldSpec((cfg.text.max_tokens, dt), f32),
        "text_mask": FieldSpec((cfg.text.max_tokens,), b),
        "view_adjacency": FieldSpec((v, v), b),
        "layout": FieldSpec((t, v, layout_channels, h, w), f32),
        "labels": FieldSpec((t, vc, MAP_PLANES, *label_hw), u8),
        "lidar_nearness": FieldSpec((t, *nearness_hw), u8),
        "range_nearness": FieldSpec((t, *range_hw), u16),
        "precipitation": FieldSpec((t, vc, *label_hw), u8),
        "precipitation_rgb": FieldSpec((t, 3), u8),
    }


def as_held(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Batched :class:`ConditionArrays` fields as :class:`Conditions` holds them: the BEV in float32,
    the range map's nearness in int32 (torch's uint16 cannot be indexed into), the rest as they are."""
    return {**batch, "bev": batch["bev"].float(), "range_nearness": batch["range_nearness"].int()}


@dataclass
class Conditions:
    """A batch of conditions as tensors: every :class:`ConditionArrays` field with a leading B,
    ``bev`` as float, plus ``drop`` (B,) bool: True replaces text and controls (ego, map,
    objects) by learned null tokens, the unconditional branch of guidance."""

    camera: torch.Tensor
    ego: torch.Tensor
    bev: torch.Tensor
    obj_corners: torch.Tensor
    obj_category: torch.Tensor
    obj_text: torch.Tensor
    obj_image: torch.Tensor
    obj_mask: torch.Tensor
    obj_has_text: torch.Tensor
    obj_has_image: torch.Tensor
    text: torch.Tensor
    text_mask: torch.Tensor
    view_adjacency: torch.Tensor
    layout: torch.Tensor
    labels: torch.Tensor
    lidar_nearness: torch.Tensor
    range_nearness: torch.Tensor
    precipitation: torch.Tensor
    precipitation_rgb: torch.Tensor
    drop: torch.Tensor

    @property
    def batch_size(self) -> int:
        return self.ego.shape[0]

    @property
    def num_frames(self) -> int:
        return self.ego.shape[1]

    @property
    def style(self) -> torch.Tensor:
        """(B, Dt) each row's scene style for the label decoder (:func:`prompt_style`)."""
        return prompt_style(self.text, self.text_mask)

    @classmethod
    def collate(cls, items: Sequence[ConditionArrays]) -> Conditions:
        """Stack sequences of equal length into a batch."""
        if len({it.num_frames for it in items}) != 1:
            raise ValueError("Conditions.collate needs sequences of equal length")
        kw = {
            f.name: torch.from_numpy(np.stack([getattr(it, f.name) for it in items])) for f in fields(ConditionArrays)
        }
        return cls(**as_held(kw), drop=torch.zeros(len(items), dtype=torch.bool))

    def apply(self, fn: Callable[[str, torch.Tensor], torch.Tensor]) -> Conditions:
        """A new batch with ``fn(field_name, tensor)`` applied to every field."""
        return Conditions(**{f.name: fn(f.name, getattr(self, f.name)) for f in fields(self)})

    def to(self, device: torch.device | str) -> Conditions:
        return self.apply(lambda _, v: v.to(device))

    def decoder_inputs(self) -> dict[str, torch.Tensor]:
        """What a decoder reads beside the latents, as keyword arguments of
        :func:`~world_model.model.sampler.latents_to_observations` and ``WorldModel.decode``: the
        frames' camera label maps, the scene's style, the LiDAR view's nearness maps and the range
        map's, and the rain or snow over the cameras."""
        return {
            "labels": self.labels,
            "style": self.style,
            "nearness": self.lidar_nearness,
            "range_nearness": self.range_nearness,
            "precipitation": self.precipitation,
            "precipitation_rgb": self.precipitation_rgb,
        }

    def frames(self, start: int, stop: int) -> Conditions:
        """Frames [start, stop) of the time-varying fields."""
        return self.apply(lambda k, v: v[:, start:stop] if k in ConditionArrays.TIME_FIELDS else v)

    def with_drop(self, drop: torch.Tensor | bool) -> Conditions:
        d = torch.as_tensor(drop, dtype=torch.bool, device=self.drop.device).expand(self.batch_size).clone()
        return replace(self, drop=d)

    @staticmethod
    def cat(items: Sequence[Conditions]) -> Conditions:
        """Concatenate along the batch (e.g. conditional + unconditional for guidance)."""
        return Conditions(**{f.name: torch.cat([getattr(it, f.name) for it in items]) for f in fields(Conditions)})
