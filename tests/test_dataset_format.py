"""The dataset's index (`dataset.json`) with several recording processes writing one dataset."""

import json
import multiprocessing

from world_model.data.clips import register_clip, sort_index


def _register_many(root: str, prefix: str) -> None:
    for k in range(25):
        register_clip(root, f"{prefix}{k:02d}")


def test_processes_registering_clips_side_by_side_lose_none_and_sort_index_orders_them(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    procs = [ctx.Process(target=_register_many, args=(str(tmp_path), p)) for p in ("b", "a", "c")]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
    assert all(p.exitcode == 0 for p in procs)
    expected = sorted(f"{p}{k:02d}" for p in "abc" for k in range(25))
    assert sort_index(tmp_path) == expected
    assert json.loads((tmp_path / "dataset.json").read_text())["clips"] == expected
