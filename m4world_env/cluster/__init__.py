"""Rollouts and evaluations spread over Ray actors, on one machine or a cluster (the ``cluster`` extra).

* :class:`RayVectorEnv`: one Gymnasium ``VectorEnv`` whose sub-envs live in ``workers`` Ray actors,
  each running a batched :class:`~m4world_env.vector.M4WorldVectorEnv` of its share; equal to the
  local vector env of the same size and seed.
* :func:`evaluate_on_ray`: :func:`m4world_env.evaluate.evaluate` of the same
  :class:`~m4world_env.evaluate.EvalRequest` with its episodes run as tasks on ``workers`` actors
  (``m4world eval --ray``); a lost worker's episodes run again elsewhere.

Ray is imported when one of them is used, so the package imports without it.
"""

from m4world_env.cluster.evaluate import EpisodeDone, EpisodeKey, EpisodeLedger, evaluate_on_ray
from m4world_env.cluster.runtime import ClusterError, connect, require_ray, split_address, split_evenly
from m4world_env.cluster.vector import RayVectorEnv

__all__ = [
    "ClusterError",
    "EpisodeDone",
    "EpisodeKey",
    "EpisodeLedger",
    "RayVectorEnv",
    "connect",
    "evaluate_on_ray",
    "require_ray",
    "split_address",
    "split_evenly",
]
