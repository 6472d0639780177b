"""The causal few-step student (paper §4.2-§4.4): KV cache, streaming engine, schedule, losses."""

from world_model.student.cache import KVCache
from world_model.student.config import StudentConfig, rollout_blocks
from world_model.student.engine import StreamingEngine, cat_frames, few_step_sample, set_rows

__all__ = [
    "KVCache",
    "StreamingEngine",
    "StudentConfig",
    "cat_frames",
    "few_step_sample",
    "rollout_blocks",
    "set_rows",
]
