"""The CPU side of a batch of rollouts: each one's first frame, reference crops and condition arrays.

One :class:`RolloutConditions` owns them for whoever streams rollouts: the env's world-model
backend (:mod:`m4world_env.backends`), each simulation worker of a vector env for its sub-envs
(:mod:`m4world_env.workers`), and the evaluation report over recorded clips
(:mod:`world_model.eval.report.rows`). The model side, which takes the arrays it builds, is
:class:`~world_model.rollout.batch.RolloutBatch`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from world_model.model.conditions import ConditionArrays
from world_model.observation import ALL_SENSORS, SensorSelection
from world_model.raster.crops import CropSource, ReferenceCrops
from world_model.rollout.builder import ConditionBuilder
from world_model.rollout.timing import StageTimer, timed
from world_model.scene import SceneFrame
from world_model.sim import ProceduralSimulator, SimConfig


class RolloutConditions:
    """Each rollout's first frame, its reference crops (cut from the procedural simulator's views by
    the rule the recorder uses, :class:`~world_model.raster.crops.ReferenceCrops`, so the model sees
    in the env the conditions it was trained on; or a recording's own) and its condition arrays, one
    step at a time. ``every_frame``: the model decodes every frame of a step, not only the last
    (:meth:`ConditionBuilder.chunk_arrays`). ``timer``: where the time of the stages ``crops`` and
    ``conditions`` goes (:mod:`world_model.rollout.timing`; none by default). ``sensors``: the
    sensors the model decodes, whose decoder maps are drawn (the camera label maps only for the
    cameras: :attr:`ConditionOptions.sensors <world_model.model.conditions.ConditionOptions.sensors>`)."""

    def __init__(
        self,
        builder: ConditionBuilder,
        num_rollouts: int,
        every_frame: bool = False,
        timer: StageTimer | None = None,
        sensors: SensorSelection = ALL_SENSORS,
    ) -> None:
        self.builder, self.every_frame, self.timer, self.sensors = builder, every_frame, timer, sensors
        self._sim = ProceduralSimulator(
            config=replace(SimConfig(), cache_size=max(SimConfig().cache_size, 2 * num_rollouts))
        )
        self._crops: list[CropSource] = [ReferenceCrops(self._sim) for _ in range(num_rollouts)]
        self._first: list[SceneFrame | None] = [None] * num_rollouts

    def restart(self, index: int, frame: SceneFrame, crops: CropSource | None = None) -> ConditionArrays:
        """Rollout ``index`` (re)starts at ``frame``; the arrays of ``frame``. Its crops start afresh,
        cut as it goes, unless ``crops`` gives them (a recording's,
        :class:`~world_model.raster.crops.RecordedCrops`)."""
        with timed(self.timer, "crops"):
            self._first[index] = frame
            source = self._crops[index] = ReferenceCrops(self._sim) if crops is None else crops
            source.update(frame)
        with timed(self.timer, "conditions"):
            return self.builder.arrays([frame], frame, source.crops, source.since, sensors=self.sensors)

    def advance(self, index: int, frames: Sequence[SceneFrame]) -> list[ConditionArrays]:
        """Rollout ``index`` moves on by a step's ``frames``: crops of objects that came into view (or
        were inserted), then the arrays of each causal chunk (:meth:`ConditionBuilder.chunk_arrays`)."""
        with timed(self.timer, "crops"):
            source = self._crops[index]
            for frame in frames:
                source.update(frame)
        with timed(self.timer, "conditions"):
            return self.builder.chunk_arrays(
                frames, self._first[index], source.crops, source.since, self.every_frame, self.sensors
            )
