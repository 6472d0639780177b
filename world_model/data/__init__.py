"""Dataset format (clips of synchronized views + LiDAR + SceneFrames) and loaders."""

from world_model.data.clips import (
    Clip,
    DatasetFormatError,
    clip_exists,
    iter_clips,
    list_clips,
    read_clip,
    register_clip,
    write_clip,
    write_json_atomic,
)

__all__ = [
    "Clip",
    "DatasetFormatError",
    "clip_exists",
    "iter_clips",
    "list_clips",
    "read_clip",
    "register_clip",
    "write_clip",
    "write_json_atomic",
]
