"""The cluster package's pure parts (no Ray needed): how sub-envs are shared, the episode ledger
that counts each episode once however often a lost worker's episodes run again, and Ray addresses."""

import socket
import time

import pytest

from m4world_env.cluster import ClusterError, EpisodeKey, EpisodeLedger, split_address, split_evenly
from m4world_env.cluster.runtime import check_reachable


def test_split_evenly_is_contiguous_and_balanced():
    assert split_evenly(5, 2) == [range(0, 3), range(3, 5)]
    assert split_evenly(4, 4) == [range(i, i + 1) for i in range(4)]
    for count, parts in [(7, 3), (64, 5), (1, 1)]:
        shares = split_evenly(count, parts)
        assert [i for s in shares for i in s] == list(range(count))
        assert max(map(len, shares)) - min(map(len, shares)) <= 1
    with pytest.raises(ValueError, match="3 items into 4"):
        split_evenly(3, 4)


def test_ledger_requeues_a_lost_workers_episodes_and_counts_each_once():
    keys = [EpisodeKey(s, e) for s in range(2) for e in range(2)]
    ledger = EpisodeLedger(keys)
    a1, a2, b1 = ledger.take("a"), ledger.take("a"), ledger.take("b")
    assert (a1, a2, b1) == (keys[0], keys[1], keys[2]) and ledger.running("a") == 2
    assert ledger.finish("a", a1, {"pdms": 1.0})
    assert ledger.lose("a") == [a2] and ledger.reruns == 1 and ledger.running("a") == 0
    assert ledger.take("c") == a2  # the lost episode runs next, elsewhere
    assert ledger.finish("c", a2, {"pdms": 0.5})
    assert not ledger.finish("a", a2, {"pdms": 0.0})  # a late duplicate is not counted
    assert ledger.done[a2] == {"pdms": 0.5}
    assert ledger.lose("c") == [] and not ledger.complete
    assert ledger.finish("b", b1, {}) and ledger.take("b") == keys[3] and ledger.finish("b", keys[3], {})
    assert ledger.complete and ledger.take("b") is None and len(ledger.done) == 4


def test_ray_addresses_are_parsed_and_one_where_nothing_listens_is_refused_at_once():
    assert split_address("auto") is None
    assert split_address("10.0.0.2:6379") == ("10.0.0.2", 6379)
    assert split_address("ray://head.local:10001") == ("head.local", 10001)
    assert split_address("[::1]:6379") == ("::1", 6379)
    for bad in ("head", "head:", ":6379", "head:port", "head:0", "head:70000", "ray://"):
        with pytest.raises(ValueError, match="give auto, HOST:PORT or ray://HOST:PORT"):
            split_address(bad)
    with socket.socket() as s:  # a port that was free a moment ago: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    started = time.monotonic()
    with pytest.raises(ClusterError, match=f"no Ray instance answers at ray://127.0.0.1:{port}"):
        check_reachable(f"ray://127.0.0.1:{port}", timeout_s=5.0)
    assert time.monotonic() - started < 5.0
