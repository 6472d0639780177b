"""A vector env's ``infos`` (Gymnasium's batched layout: ``key`` -> array over sub-envs, ``_key`` -> which
sub-envs have it, nested dicts alike) back into one info dict per sub-env.

:meth:`gymnasium.vector.VectorEnv._add_info` batches; :func:`unbatch_infos` inverts it, so infos can be
re-batched under other indices (several vector envs presented as one) or handed to libraries that take
a list of per-env dicts (Stable-Baselines3).
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _is_mask(key: str, infos: dict[str, Any]) -> bool:
    return key.startswith("_") and key[1:] in infos


def unbatch_infos(infos: dict[str, Any], num_envs: int) -> list[dict[str, Any]]:
    """``infos`` of a vector env of ``num_envs`` sub-envs -> one dict per sub-env with the keys it has."""
    out: list[dict[str, Any]] = [{} for _ in range(num_envs)]
    for key, value in infos.items():
        if _is_mask(key, infos):
            continue
        mask = infos.get(f"_{key}")
        if mask is None:
            raise ValueError(f"vector info {key!r} has no mask '_{key}': not a Gymnasium vector env's infos")
        nested = unbatch_infos(value, num_envs) if isinstance(value, dict) else None
        for i in range(num_envs):
            if mask[i]:
                out[i][key] = nested[i] if nested is not None else _item(value[i])
    return out


def _item(value: Any) -> Any:
    # Gymnasium batches a bool into a bool array but a numpy bool (not an np.number) into an object
    # array: give the bool back so that re-batching yields the same layout.
    return bool(value) if isinstance(value, np.bool_) else value
