"""Reference crops of a rollout: each object's "image description" (paper §3.2), cut causally.

The recorder (training data) and the world-model env (serving) must give the model the same
image descriptions for the same scene. The env cannot look ahead, so the rule uses only frames up
to the current one: every ``every_frames`` frames (frame indices divisible by it), the objects that
have no crop yet get the simulator's :meth:`~world_model.sim.ProceduralSimulator.object_crops` of
that frame, and keep it for the rest of the rollout. A track's crop conditions the frames from the
one it was cut at (``since``), so training on a recorded clip sees it exactly where the env would.
An object whose scenario names an image file (``image_path``) gets that image instead, from the
first frame it is in; an object carrying its own in-memory ``image`` needs no crop.

A recording keeps the crops it cut (a clip's ``crops`` and ``crop_since``): :class:`RecordedCrops`
replays them, so a rollout over a recorded clip is conditioned on exactly what training saw.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

import cv2
import numpy as np

from world_model.scene import SceneFrame
from world_model.sim.simulator import ProceduralSimulator

# One look per second at 10 Hz: a rollout's cameras are rendered for crops at most this often.
CROP_EVERY_FRAMES = 10


class CropSource(Protocol):
    """A rollout's reference crops so far: ``crops`` by track id, ``since`` the frame index from
    which each conditions the frames (a track absent from ``since`` has its crop at every frame)."""

    crops: dict[str, np.ndarray]
    since: dict[str, int]

    def update(self, frame: SceneFrame, cameras: np.ndarray | None = None) -> None:
        """The rollout reached ``frame`` (``cameras``: its rendered images if at hand)."""


class ReferenceCrops:
    """The crops cut so far in one rollout (``crops`` by track id, ``since`` their frame index)."""

    def __init__(self, sim: ProceduralSimulator, every_frames: int = CROP_EVERY_FRAMES) -> None:
        if every_frames < 1:
            raise ValueError(f"every_frames must be >= 1, got {every_frames}")
        self.sim, self.every_frames = sim, every_frames
        self.crops: dict[str, np.ndarray] = {}
        self.since: dict[str, int] = {}
        self._files: dict[str, np.ndarray] = {}

    def _read(self, track_id: str, path: str) -> np.ndarray:
        if path not in self._files:
            img = cv2.imread(path, cv2.IMREAD_COLOR)
            if img is None:
                raise FileNotFoundError(f"object {track_id!r}: image {path} cannot be read")
            self._files[path] = img[..., ::-1].copy()
        return self._files[path]

    def update(self, frame: SceneFrame, cameras: np.ndarray | None = None) -> None:
        """Cut crops of ``frame``'s objects that have none (and no image of their own) when the
        frame's index is a crop frame; ``cameras`` are its rendered images if at hand."""
        for o in frame.objects:
            if o.track_id not in self.crops and o.image is None and o.image_path:
                self.crops[o.track_id], self.since[o.track_id] = self._read(o.track_id, o.image_path), frame.frame_index
        if frame.frame_index % self.every_frames:
            return
        if all(o.track_id in self.crops or o.image is not None for o in frame.objects):
            return
        for tid, crop in self.sim.object_crops(frame, cameras).items():
            if tid not in self.crops:
                self.crops[tid], self.since[tid] = crop, frame.frame_index


class RecordedCrops:
    """The crops of a recorded rollout, given whole: none is cut as the rollout goes on."""

    def __init__(self, crops: Mapping[str, np.ndarray] | None = None, since: Mapping[str, int] | None = None) -> None:
        self.crops: dict[str, np.ndarray] = dict(crops or {})
        self.since: dict[str, int] = dict(since or {})

    def update(self, frame: SceneFrame, cameras: np.ndarray | None = None) -> None:
        """Nothing to cut: the recording cut every crop it has."""
