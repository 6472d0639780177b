"""``m4world eval --ray``: the evaluation harness with its episodes run as tasks on Ray actors.

It takes the local harness's :class:`~m4world_env.evaluate.EvalRequest`. Each episode is one task,
identified by :class:`EpisodeKey` (its scenario's position and its index; its seed is
``seed + index`` as in :func:`m4world_env.evaluate.evaluate`). Workers are Ray actors that
keep one scenario's env and policy between episodes and have at most :data:`QUEUE_PER_WORKER` episodes
queued. When a worker is lost (actor killed, node gone), its unfinished episodes go back to the queue
and a fresh worker takes its place; results are kept by key, so every episode counts exactly once and
the report, table and per-episode seeds are the local harness's own. A policy whose state carries
from one episode to the next of a scenario (none of the built-ins) can differ, since a worker runs
some of a scenario's episodes, not all of them in order.
"""

from __future__ import annotations

import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Any

from m4world_env.cluster.runtime import (
    WORKER_START_TIMEOUT_S,
    ClusterError,
    check_capacity,
    connect,
    require_ray,
)
from m4world_env.config import EnvConfig
from m4world_env.evaluate import EvalRequest, build_report, run_episode, scenario_policy
from m4world_env.scenario import Scenario, load_scenario

QUEUE_PER_WORKER = 2  # episodes queued on a worker: the next one is there when one finishes


@dataclass(frozen=True, order=True)
class EpisodeKey:
    """An episode's identity: its scenario's position in the evaluation's list, and its index there."""

    scenario: int
    episode: int


@dataclass(frozen=True)
class EpisodeDone:
    """An episode counted in the report: which, on which worker (the Ray actor's name), its metrics."""

    key: EpisodeKey
    scenario: str
    seed: int
    worker: str
    metrics: dict[str, float]


class EpisodeLedger:
    """Which episodes wait, which run on which worker, which are done (each once, by key)."""

    def __init__(self, keys: Iterable[EpisodeKey]) -> None:
        self._waiting = deque(keys)
        self._total = len(set(self._waiting))
        self._running: dict[str, list[EpisodeKey]] = {}
        self.done: dict[EpisodeKey, dict[str, float]] = {}
        self.reruns = 0  # episodes that went back to the queue from a lost worker

    @property
    def complete(self) -> bool:
        return len(self.done) == self._total

    def running(self, worker: str) -> int:
        return len(self._running.get(worker, ()))

    def take(self, worker: str) -> EpisodeKey | None:
        """The next waiting episode, now running on ``worker``; None when none waits."""
        while self._waiting:
            key = self._waiting.popleft()
            if key not in self.done:
                self._running.setdefault(worker, []).append(key)
                return key
        return None

    def finish(self, worker: str, key: EpisodeKey, metrics: dict[str, float]) -> bool:
        """Record ``key``'s result from ``worker``; False (and nothing recorded) if it was done already."""
        running = self._running.get(worker, [])
        if key in running:
            running.remove(key)
        if key in self.done:
            return False
        self.done[key] = metrics
        return True

    def lose(self, worker: str) -> list[EpisodeKey]:
        """``worker`` is gone: its unfinished episodes wait again, first in the queue; returns them."""
        unfinished = [k for k in self._running.pop(worker, []) if k not in self.done]
        self._waiting.extendleft(reversed(unfinished))
        self.reruns += len(unfinished)
        return unfinished


class EpisodeRunner:
    """What one Ray actor holds: the env and policy of the scenario it last ran. Built lazily, in
    :meth:`run`, so that a bad option fails the task with its own error instead of the actor."""

    def __init__(self, request: EvalRequest, threads: int) -> None:
        import torch

        torch.set_num_threads(threads)
        self.request = request
        self._scenario: int | None = None
        self._env: Any = None
        self._episode_policy: Any = None

    def ready(self) -> bool:
        return True

    def run(self, scenario_index: int, scenario: Scenario, seed: int) -> dict[str, float]:
        r = self.request
        if scenario_index != self._scenario:
            import gymnasium as gym

            if self._env is not None:
                self._env.close()
            self._env = gym.make(
                "M4World-v0", scenario=scenario, backend=r.backend, checkpoint=r.checkpoint, config=r.config
            )
            self._episode_policy = scenario_policy(r.policy, self._env)
            self._scenario = scenario_index
        return run_episode(self._env, self._episode_policy, seed=seed, max_steps=r.max_steps)


class WorkerPool:
    """The evaluation's Ray actors and their calls in flight: it starts workers, keeps each fed with
    up to :data:`QUEUE_PER_WORKER` episodes of the ledger, and replaces a lost one."""

    def __init__(
        self,
        ray: Any,
        request: EvalRequest,
        scenarios: list[Scenario],
        cpus_per_worker: float,
        start_timeout_s: float = WORKER_START_TIMEOUT_S,
    ) -> None:
        self.ray, self.request, self.scenarios = ray, request, scenarios
        self.cpus_per_worker = cpus_per_worker
        self.start_timeout_s = start_timeout_s
        self.up: set[str] = set()  # workers that answered `ready` and are not lost
        self.start_deadline = 0.0
        self._runner = ray.remote(EpisodeRunner)
        self._prefix = f"m4world-eval-{uuid.uuid4().hex[:8]}"
        self.handles: dict[str, Any] = {}
        self.calls: dict[Any, tuple[str, EpisodeKey | None]] = {}  # object ref -> (worker, episode; None: ready)
        self.started = 0
        self.losses = 0

    def start(self) -> None:
        """A fresh worker, named after the pool and its rank."""
        name = f"{self._prefix}-{self.started}"
        self.started += 1
        self.start_deadline = time.monotonic() + self.start_timeout_s
        options = self._runner.options(name=name, num_cpus=self.cpus_per_worker)
        self.handles[name] = options.remote(self.request, max(1, int(self.cpus_per_worker)))
        self.calls[self.handles[name].ready.remote()] = (name, None)

    def feed(self, name: str, ledger: EpisodeLedger) -> None:
        """Queue waiting episodes of ``ledger`` on worker ``name``, up to :data:`QUEUE_PER_WORKER`."""
        while ledger.running(name) < QUEUE_PER_WORKER and (key := ledger.take(name)) is not None:
            seed = self.request.seed + key.episode
            self.calls[self.handles[name].run.remote(key.scenario, self.scenarios[key.scenario], seed)] = (name, key)

    def run(
        self, ledger: EpisodeLedger, limit: int, bar: Any, on_episode: Callable[[EpisodeDone], None] | None
    ) -> None:
        """Until every episode of ``ledger`` is done: count each result once, put a lost worker's
        episodes back and replace it (more than ``limit`` losses stop the evaluation)."""
        ray = self.ray
        while not ledger.complete:
            # Ray reports a lost worker; a worker that never starts is bounded here.
            deadline = None if self.up else self.start_deadline
            ref = _first_done(ray, list(self.calls), deadline, self.start_timeout_s)
            name, key = self.calls.pop(ref)
            if name not in self.handles:
                continue  # a call of a worker already counted lost
            try:
                metrics = ray.get(ref)
            except ray.exceptions.RayActorError as e:
                self._lose(name, ledger, limit, e)
                continue
            done = None
            if key is None:
                self.up.add(name)
            elif ledger.finish(name, key, metrics):
                bar.update()
                seed = self.request.seed + key.episode
                done = EpisodeDone(key, self.scenarios[key.scenario].name, seed, name, metrics)
            self.feed(name, ledger)
            if done is not None and on_episode is not None:
                on_episode(done)

    def _lose(self, name: str, ledger: EpisodeLedger, limit: int, error: Exception) -> None:
        self.losses += 1
        self.up.discard(name)
        self.ray.kill(self.handles.pop(name))
        for other in [r for r, (n, _) in self.calls.items() if n == name]:
            del self.calls[other]
        ledger.lose(name)
        if self.losses > limit:
            raise RuntimeError(
                f"{self.losses} Ray workers lost (more than max_worker_losses={limit}); the last: {error}"
            ) from error
        self.start()

    def close(self) -> None:
        for handle in self.handles.values():
            self.ray.kill(handle)


def evaluate_on_ray(
    request: EvalRequest,
    progress: bool = True,
    workers: int | None = None,
    address: str | None = None,
    cpus_per_worker: float = 1.0,
    max_worker_losses: int | None = None,
    on_episode: Callable[[EpisodeDone], None] | None = None,
    start_timeout_s: float = WORKER_START_TIMEOUT_S,
) -> dict[str, Any]:
    """:func:`m4world_env.evaluate.evaluate` of ``request`` on ``workers`` Ray actors (default: one
    per CPU of the instance), joined at ``address`` (:func:`~m4world_env.cluster.connect`). Returns
    the same report plus ``report["cluster"]``: workers, workers lost, episodes re-run. Lost workers
    are replaced up to ``max_worker_losses`` times (default ``workers``), then the evaluation stops
    with an error. ``on_episode`` is called with each episode counted, as it is counted. No wait is
    unbounded while no worker runs: an address where nothing answers
    (:func:`~m4world_env.cluster.connect`), more workers than the instance's CPUs hold, or no worker
    started within ``start_timeout_s`` of its start is a :class:`~m4world_env.cluster.ClusterError`."""
    from tqdm import tqdm

    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers must be a positive integer or None (one per CPU), got {workers!r}")
    config = request.config
    request = replace(request, config=config if isinstance(config, EnvConfig) else EnvConfig.from_dict(config))
    loaded = [load_scenario(s) for s in request.scenarios]  # here: a file path need not exist on the workers
    ray = require_ray()
    owns_ray = connect(address)
    pool = WorkerPool(ray, request, loaded, cpus_per_worker, start_timeout_s)
    ledger = EpisodeLedger(EpisodeKey(s, e) for s in range(len(loaded)) for e in range(request.episodes))
    try:
        count = workers or max(1, int(ray.cluster_resources().get("CPU", 1) // cpus_per_worker))
        check_capacity(ray, count, cpus_per_worker)
        for _ in range(count):
            pool.start()
        bar = tqdm(total=len(loaded) * request.episodes, desc="episodes", unit="ep", disable=not progress)
        pool.run(ledger, count if max_worker_losses is None else max_worker_losses, bar, on_episode)
        bar.close()
    finally:
        pool.close()
        if owns_ray:
            ray.shutdown()
    episodes = range(request.episodes)
    results = [(sc.name, [ledger.done[EpisodeKey(i, e)] for e in episodes]) for i, sc in enumerate(loaded)]
    report = build_report(request, results)
    report["cluster"] = {"workers": count, "workers_lost": pool.losses, "episodes_rerun": ledger.reruns}
    return report


def _first_done(ray: Any, refs: list[Any], deadline: float | None, start_timeout_s: float) -> Any:
    """The first of ``refs`` to finish; while no worker runs (``deadline`` set), a
    :class:`ClusterError` once ``deadline`` (``time.monotonic()``) passes."""
    timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
    ready, _ = ray.wait(refs, num_returns=1, timeout=timeout)
    if not ready:
        raise ClusterError(
            f"no Ray worker started within {start_timeout_s:g} s (the instance has no free CPUs for them, "
            "or their start hangs)"
        )
    return ready[0]
