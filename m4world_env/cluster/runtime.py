"""Ray itself: importing it with an actionable error, joining or starting an instance within a
timeout, checking what it can hold, waiting for workers to start, sharing work."""

from __future__ import annotations

import os
import socket
from collections.abc import Sequence
from types import ModuleType
from typing import Any

# Ray retries an address where nothing answers for minutes: a port that does not accept a TCP
# connection within this time is refused before Ray is asked.
CONNECT_TIMEOUT_S = 10.0
# A worker imports torch and builds its env (a world model included) before it answers; one that
# has not answered by then waits for resources the instance does not give it.
WORKER_START_TIMEOUT_S = 300.0
# Closing workers that never started must not wait for them.
CLOSE_TIMEOUT_S = 30.0
ADDRESS_FORMS = "auto, HOST:PORT or ray://HOST:PORT"


class ClusterError(ConnectionError):
    """Ray could not be joined, or its workers did not start within their timeout."""


def require_ray() -> ModuleType:
    """The ``ray`` module, or an ImportError that says how to install it."""
    try:
        import ray
    except ImportError as e:
        raise ImportError(
            "the cluster features need Ray: pip install 'm4world-gym[cluster]' (or pip install 'ray>=2.50,<3')"
        ) from e
    return ray


def split_address(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of a Ray address (``"HOST:PORT"`` or ``"ray://HOST:PORT"``); None for ``"auto"``
    (Ray finds the instance). A ValueError naming the address otherwise."""
    if address == "auto":
        return None
    rest = address.removeprefix("ray://")
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 2**16:
        raise ValueError(f"Ray address {address!r}: give {ADDRESS_FORMS}")
    return host.strip("[]"), int(port)


def check_reachable(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Refuse, within ``timeout_s``, a Ray address (:func:`split_address`) where nothing accepts a
    connection: a :class:`ClusterError` naming it."""
    target = split_address(address)
    if target is None:
        return
    try:
        socket.create_connection(target, timeout=timeout_s).close()
    except OSError as e:
        reason = f"no answer within {timeout_s:g} s" if isinstance(e, TimeoutError) else (e.strerror or str(e)).lower()
        raise ClusterError(
            f"no Ray instance answers at {address} ({reason}): start one there (ray start --head) or give "
            "the address of a running one"
        ) from None


def connect(address: str | None, timeout_s: float = CONNECT_TIMEOUT_S) -> bool:
    """Join the Ray instance at ``address`` (``"auto"``, ``"HOST:PORT"``, ``"ray://HOST:10001"``), or with
    ``None`` the one ``RAY_ADDRESS`` names, else a new local one. An address where nothing answers
    within ``timeout_s`` is a :class:`ClusterError`, as is one Ray refuses. A process already
    connected stays on its instance. Returns whether this call connected (the caller then owns the
    connection and ends it with ``ray.shutdown()``)."""
    ray = require_ray()
    if ray.is_initialized():
        return False
    # Ray reads RAY_ADDRESS where no address, or "auto", is given.
    named = os.environ.get("RAY_ADDRESS") if address in (None, "", "auto") else address
    if named:
        check_reachable(named, timeout_s)
    try:
        ray.init(address=address or None)
    except (ConnectionError, ValueError) as e:
        where = f"Ray address {named or address}" if named or address else "a new local Ray instance"
        raise ClusterError(f"{where}: {e}") from e
    return True


def check_capacity(ray: ModuleType, workers: int, cpus_per_worker: float) -> None:
    """Refuse ``workers`` actors of ``cpus_per_worker`` CPUs each that the connected instance cannot
    hold at once (they would wait for CPUs forever)."""
    cpus = float(ray.cluster_resources().get("CPU", 0.0))
    most = int(cpus // cpus_per_worker)
    if workers > most:
        raise ClusterError(
            f"workers={workers} of {cpus_per_worker:g} CPU each need {workers * cpus_per_worker:g} CPUs; "
            f"the Ray instance has {cpus:g}: ask for at most {most} workers (or add nodes)"
        )


def wait_started(ray: ModuleType, refs: Sequence[Any], timeout_s: float = WORKER_START_TIMEOUT_S) -> list[Any]:
    """The results of the workers' first calls ``refs``, or a :class:`ClusterError` when not all of
    them have answered within ``timeout_s`` (an error a worker raised is raised as it is)."""
    ready, waiting = ray.wait(list(refs), num_returns=len(refs), timeout=timeout_s)
    if waiting:
        raise ClusterError(
            f"{len(waiting)} of {len(refs)} Ray workers did not start within {timeout_s:g} s "
            "(the instance has no free CPUs for them, or their start hangs)"
        )
    return ray.get(list(refs))


def split_evenly(count: int, parts: int) -> list[range]:
    """``range(count)`` cut into ``parts`` contiguous ranges whose sizes differ by at most one, the
    larger first: ``split_evenly(5, 2) == [range(0, 3), range(3, 5)]``."""
    if not 1 <= parts <= count:
        raise ValueError(f"cannot split {count} items into {parts} non-empty parts (need 1 <= parts <= {count})")
    base, extra = divmod(count, parts)
    bounds = [0]
    for k in range(parts):
        bounds.append(bounds[-1] + base + (k < extra))
    return [range(a, b) for a, b in zip(bounds, bounds[1:], strict=False)]
