"""The rolling KV cache against a hand-worked timeline: window eviction, sink frames, the
refresh's left-out newest frame, and a restarted row (what every env step of the default
4-frame window exercises)."""

import torch

from world_model.student.cache import KVCache


def frame_ids(ids_per_row: list[list[int]]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """One layer's K/V (rows*V, H=1, frames*N, hd=1) whose entries are the frames' ids (N = V = 1)."""
    k = torch.tensor(ids_per_row, dtype=torch.float32)[:, None, :, None]
    return [(k, -k)]


def context_ids(cache: KVCache, exclude_newest: bool = False) -> tuple[list[list[int]], list[list[bool]] | None]:
    layers, valid = cache.context(exclude_newest)
    k, v = layers[0]
    assert torch.equal(v, -k)  # values travel with their keys
    return k[:, 0, :, 0].int().tolist(), None if valid is None else valid.tolist()


def test_window_sink_refresh_and_restart_follow_the_timeline():
    cache = KVCache(batch=2, views=1, tokens_per_frame=1, window=3, sink=1)
    for f in range(6):
        cache.append(frame_ids([[f], [100 + f]]), frames=1)
    # the sink keeps each row's first frame, the window its three newest
    assert context_ids(cache) == ([[0, 3, 4, 5], [100, 103, 104, 105]], None)
    # context refresh recomputes the newest frame with the chunk: the cache leaves it out
    assert context_ids(cache, exclude_newest=True) == ([[0, 3, 4], [100, 103, 104]], None)

    cache.restart_rows([1], frame_ids([[500]]), frames=1)
    ids, valid = context_ids(cache)
    assert ids[0] == [0, 3, 4, 5] and ids[1][-1] == 500
    assert valid == [[True] * 4, [False, False, False, True]]  # row 1's old frames are gone

    for f in range(3):
        cache.append(frame_ids([[6 + f], [501 + f]]), frames=1)
    # row 1's first frame left its window and now sits in the sink
    assert context_ids(cache) == ([[0, 6, 7, 8], [500, 501, 502, 503]], None)


def test_a_sink_frame_is_not_attended_twice_and_memory_is_fixed():
    cache = KVCache(batch=1, views=1, tokens_per_frame=1, window=3, sink=1)
    cache.append(frame_ids([[0, 1]]), frames=2)
    # frame 0 is still in the window: its sink slot stays invalid and unused
    assert context_ids(cache) == ([[0, 1]], None)
    size = cache.nbytes()
    for f in range(2, 40):
        cache.append(frame_ids([[f]]), frames=1)
        assert cache.nbytes() == size
    assert context_ids(cache) == ([[0, 37, 38, 39]], None)
