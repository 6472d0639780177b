"""Ray itself: importing it with an actionable error, joining or starting an instance, sharing work."""

from __future__ import annotations

from types import ModuleType


def require_ray() -> ModuleType:
    """The ``ray`` module, or an ImportError that says how to install it."""
    try:
        import ray
    except ImportError as e:
        raise ImportError(
            "the cluster features need Ray: pip install 'm4world-gym[cluster]' (or pip install 'ray>=2.50,<3')"
        ) from e
    return ray


def connect(address: str | None) -> bool:
    """Join the Ray instance at ``address`` (``"auto"``, ``"HOST:PORT"``, ``"ray://HOST:10001"``), or with
    ``None`` the one ``RAY_ADDRESS`` names, else a new local one. A process already connected stays
    on its instance. Returns whether this call connected (the caller then owns the connection and
    ends it with ``ray.shutdown()``)."""
    ray = require_ray()
    if ray.is_initialized():
        return False
    ray.init(address=address or None)
    return True


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
