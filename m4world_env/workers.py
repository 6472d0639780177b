"""Simulation workers: a world-model vector env's CPU side in worker processes beside one model.

With ``config={"workers": K}``, :class:`~m4world_env.vector.M4WorldVectorEnv` splits its sub-envs
into K contiguous slices, one per worker process (``spawn``). A worker owns its sub-envs' traffic,
episode state, rewards and infos, cuts their reference crops and builds their condition arrays
(:class:`~world_model.rollout.conditions.RolloutConditions`, the code the in-process backend runs); the
main process keeps the batched student, the reference model and the VAE decoder. A step:

1. main sends each worker its actions; every worker checks them (a bad one anywhere refuses the
   step before any sub-env moves);
2. the workers advance their sub-envs (or restart those whose episode ended), write the condition
   arrays and ``state`` observations into shared memory (:mod:`m4world_env.shared_arrays`) and
   send back rewards, flags and infos;
3. main runs one batched student step and one decode over all sub-envs, the batched first frames
   of restarted ones, and assembles the observations.

The pipes carry actions, rewards, flags and infos; a SceneFrame crosses them only when an episode
starts (its first frame, for the reference model). Results equal the in-process vector env's bit
for bit on CPU: the workers run the same code at the main process's torch thread count. On a GPU
the workers encode the reference crops on CPU, the in-process backend on the device: equal up to
float rounding.
"""

from __future__ import annotations

import pickle
import signal
import threading
import time
import traceback
import weakref
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass, fields
from multiprocessing import current_process, get_context
from multiprocessing.connection import Connection, wait
from typing import Any

import numpy as np
from gymnasium.error import ResetNeeded

from m4world_env.backends import WorldModelBackend
from m4world_env.config import EnvConfig
from m4world_env.env import STATE_FEATURES, M4WorldEnv, decoded_sensors, observation_dict
from m4world_env.scenario import Scenario
from m4world_env.shared_arrays import SharedArrays, SharedLayout
from world_model.model.conditions import ConditionArrays, condition_field_specs
from world_model.model.config import ModelConfig
from world_model.rollout.builder import ConditionBuilder
from world_model.rollout.conditions import RolloutConditions
from world_model.rollout.timing import StageTimer
from world_model.scene import SceneFrame

START_TIMEOUT_S = 300.0  # the workers import torch and build their encoders
REPLY_TIMEOUT_S = 1800.0  # live workers that have not answered a request by then are stuck
JOIN_TIMEOUT_S = 5.0  # a closing worker (or spec sender) that takes longer is stopped harder
# Spawned workers import the main module: a script that makes the vector env at its top level
# makes it again inside each worker, which then exits.
MAIN_GUARD_HINT = (
    "config.workers starts worker processes, which import the main script; a script that makes the "
    "vector env needs `if __name__ == '__main__':` around its code"
)
OBJECT_METHODS = ("insert_object", "remove_object", "edit_object")
WORKER_COMMANDS = ("reset", "check", "advance", "call", "seconds")  # SimulationWorker methods main may call


class SimulationWorkerError(RuntimeError):
    """A simulation worker died, hung or could not start; the vector env cannot go on."""


class RemoteTraceback(Exception):
    """The traceback of an exception raised in a simulation worker (the cause of the one raised)."""


@dataclass(frozen=True)
class EpisodeStart:
    """A sub-env's episode (re)started in a worker: its first frame and the model's seed."""

    frame: SceneFrame
    seed: int


@dataclass(frozen=True)
class SubEnvReport:
    """What a worker reports of one sub-env after a step or reset (its sensors are main's)."""

    reward: float
    terminated: bool
    truncated: bool
    info: dict[str, Any]
    start: EpisodeStart | None  # set when the sub-env (re)started


@dataclass(frozen=True)
class WorkerSpec:
    """Everything a worker process starts from (pickled once, at its start)."""

    index: int
    rows: tuple[int, int]  # its sub-envs: [rows[0], rows[1])
    scenario: Scenario
    config: EnvConfig
    model_config: ModelConfig
    vae_weights: dict[str, np.ndarray]
    layout: SharedLayout
    torch_threads: int


def check_main_guard() -> None:
    """Refuse to start workers from a process that is itself starting (a spawned process importing
    a main script without a main guard): a :class:`SimulationWorkerError` with the hint."""
    if getattr(current_process(), "_inheriting", False):  # set by multiprocessing while it imports
        raise SimulationWorkerError(MAIN_GUARD_HINT)


def worker_rows(num_envs: int, num_workers: int) -> list[tuple[int, int]]:
    """Contiguous slices [lo, hi) of ``num_envs`` sub-envs over ``num_workers`` workers, sizes
    differing by at most one."""
    bounds = [k * num_envs // num_workers for k in range(num_workers + 1)]
    return list(zip(bounds[:-1], bounds[1:], strict=True))


def shared_array_shapes(
    model_config: ModelConfig, num_envs: int, chunks_per_step: int, state_objects: int | None
) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """The shared arrays of a vector env: per sub-env, each condition field of a step's chunks
    (``step.<field>``, (N, chunks, ...)) and of an episode's first frame (``first.<field>``), and
    the ``state`` observation when the env observes it (``state_objects`` not None)."""
    step = condition_field_specs(model_config, model_config.clip.chunk_frames)
    first = condition_field_specs(model_config, 1)
    shapes = {f"step.{k}": ((num_envs, chunks_per_step, *s.shape), s.dtype) for k, s in step.items()}
    shapes |= {f"first.{k}": ((num_envs, *s.shape), s.dtype) for k, s in first.items()}
    if state_objects is not None:
        shapes["state"] = ((num_envs, 1 + state_objects, len(STATE_FEATURES)), np.dtype(np.float32))
    return shapes


def write_arrays(slots: dict[str, np.ndarray], prefix: str, index: tuple[int, ...], arrays: ConditionArrays) -> None:
    """Copy every field of ``arrays`` into ``slots[prefix + field][index]``, refusing a shape the
    layout does not hold (numpy would broadcast it silently)."""
    for f in fields(ConditionArrays):
        target, value = slots[prefix + f.name][index], getattr(arrays, f.name)
        if value.shape != target.shape:
            raise ValueError(f"condition field {f.name} has shape {value.shape}, the shared layout {target.shape}")
        target[...] = value


def read_arrays(slots: dict[str, np.ndarray], prefix: str, rows: Sequence[int]) -> dict[str, np.ndarray]:
    """A copy of every ``prefix`` field's rows ``rows`` (the workers overwrite the slots later)."""
    return {f.name: slots[prefix + f.name][list(rows)] for f in fields(ConditionArrays)}


def _arrays_at(block: dict[str, np.ndarray], index: tuple[int, ...]) -> ConditionArrays:
    return ConditionArrays(**{k: v[index] for k, v in block.items()})


# ---------------------------------------------------------------------------------------- worker


class WorkerBackend:
    """The backend a worker's sub-envs are built on: the checkpoint's sensors, no model (their
    sensors are rendered in the main process)."""

    def __init__(self, model_config: ModelConfig) -> None:
        self.model_cfg = model_config
        self.rig = model_config.sensors.rig()

    def reset(self, *_: Any) -> None:
        raise RuntimeError("a simulation worker's sub-env is reset by its vector env, not by env.reset()")

    reset_many = step = reset


class SimulationWorker:
    """The sub-envs of one worker process and what it does with them, command by command."""

    def __init__(self, spec: WorkerSpec, shared: SharedArrays) -> None:
        lo, hi = spec.rows
        self.lo, self.slots = lo, shared.arrays
        self.keys = spec.config.observation_keys
        builder = ConditionBuilder.from_vae_weights(spec.model_config, spec.vae_weights)
        # A worker's sub-envs never render (render_mode needs workers=0): only each step's last frame
        # is decoded, of the sensors observed.
        sensors = decoded_sensors(self.keys, None)
        self.conditions = RolloutConditions(builder, hi - lo, every_frame=False, timer=StageTimer(), sensors=sensors)
        backend = WorkerBackend(spec.model_config)
        self.envs = [
            M4WorldEnv(spec.scenario, "world_model", None, None, spec.config, shared_backend=backend, backend_index=i)
            for i in range(hi - lo)
        ]
        self._checked: tuple[list[Any], np.ndarray] | None = None  # the actions of the step to advance
        self.traffic_s = self.busy_s = self.busy_cpu_s = 0.0

    def seconds(self) -> dict[str, float]:
        """Wall seconds of the sub-envs' traffic, crops and condition arrays so far, of whole steps
        and resets (``busy``: those, rewards, infos, shared-memory writes), and the CPU seconds this
        process got meanwhile (``busy_cpu``: below ``busy`` when other processes took its core)."""
        stages = self.conditions.timer.seconds
        return {
            "traffic": self.traffic_s,
            "crops": stages["crops"],
            "conditions": stages["conditions"],
            "busy": self.busy_s,
            "busy_cpu": self.busy_cpu_s,
        }

    def reset(self, local: Sequence[int], seeds: Sequence[int | None], options: dict | None) -> list[SubEnvReport]:
        t0, c0 = time.perf_counter(), time.process_time()
        reports = [self._start(i, seed, options) for i, seed in zip(local, seeds, strict=True)]
        self.busy_s += time.perf_counter() - t0
        self.busy_cpu_s += time.process_time() - c0
        return reports

    def check(self, actions: Sequence[Any], restarting: np.ndarray) -> None:
        self._checked = None
        for i, (env, action) in enumerate(zip(self.envs, actions, strict=True)):
            if not restarting[i]:
                with _blame(i):
                    env.check_action(action)
        self._checked = (list(actions), restarting)

    def advance(self) -> list[SubEnvReport]:
        if self._checked is None:
            raise RuntimeError("advance without a checked step")
        (actions, restarting), self._checked = self._checked, None
        t_start, c_start = time.perf_counter(), time.process_time()
        reports = []
        for i, (env, action) in enumerate(zip(self.envs, actions, strict=True)):
            with _blame(i):
                if restarting[i]:
                    reports.append(self._start(i, None, None))
                    continue
                t0 = time.perf_counter()
                frames = env.advance(action)
                self.traffic_s += time.perf_counter() - t0
                for k, arrays in enumerate(self.conditions.advance(i, frames)):
                    write_arrays(self.slots, "step.", (self.lo + i, k), arrays)
                reward, terminated, truncated, info = env.settle_step(frames)
                self._write_state(i, env)
                reports.append(SubEnvReport(reward, terminated, truncated, info, None))
        self.busy_s += time.perf_counter() - t_start
        self.busy_cpu_s += time.process_time() - c_start
        return reports

    def call(self, local: int, method: str, args: tuple, kwargs: dict) -> Any:
        if method not in OBJECT_METHODS:
            raise AttributeError(f"a sub-env in a simulation worker offers {OBJECT_METHODS}, not {method!r}")
        with _blame(local):
            return getattr(self.envs[local], method)(*args, **kwargs)

    def _start(self, i: int, seed: int | None, options: dict | None) -> SubEnvReport:
        env = self.envs[i]
        with _blame(i):
            t0 = time.perf_counter()
            frame, _, model_seed = env.begin_reset(seed=seed, options=options)
            self.traffic_s += time.perf_counter() - t0
            write_arrays(self.slots, "first.", (self.lo + i,), self.conditions.restart(i, frame))
            info = env.start_episode()
            self._write_state(i, env)
        return SubEnvReport(0.0, False, False, info, EpisodeStart(frame, model_seed))

    def _write_state(self, i: int, env: M4WorldEnv) -> None:
        if "state" in self.keys:
            self.slots["state"][self.lo + i] = env.state_observation()


@contextmanager
def _blame(local: int) -> Iterator[None]:
    """Tags an exception raised inside with the worker-local sub-env index it concerns."""
    try:
        yield
    except Exception as e:
        if not hasattr(e, "m4world_local_env"):
            e.m4world_local_env = local
        raise


def run_worker(conn: Connection) -> None:
    """A worker process's body: receive its :class:`WorkerSpec`, build the sub-envs, then answer
    commands until "close"."""
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle (it closes us)
    try:
        spec: WorkerSpec = conn.recv()
    except EOFError:  # the main process gave up on the start
        return
    torch.set_num_threads(spec.torch_threads)  # as main's: the encoders' numbers depend on it
    shared = SharedArrays.attach(spec.layout)
    try:
        try:
            worker = SimulationWorker(spec, shared)
        except Exception as e:  # noqa: BLE001 (sent to the main process, which raises it)
            conn.send(("error", _portable(e), traceback.format_exc()))
            return
        conn.send(("ok", None))
        while True:
            try:
                command, args = conn.recv()
            except EOFError:  # the main process is gone
                return
            if command == "close":
                return
            try:
                if command not in WORKER_COMMANDS:
                    raise ValueError(f"unknown simulation worker command {command!r}; known: {WORKER_COMMANDS}")
                conn.send(("ok", getattr(worker, command)(*args)))
            except Exception as e:  # noqa: BLE001 (sent to the main process, which raises it)
                conn.send(("error", _portable(e), traceback.format_exc()))
    finally:
        shared.close()


def _portable(error: Exception) -> Exception:
    """``error`` if it pickles, else a RuntimeError naming it (with its sub-env tag)."""
    try:
        pickle.loads(pickle.dumps(error))
        return error
    except Exception:  # noqa: BLE001 (any pickling failure)
        portable = RuntimeError(f"{type(error).__name__}: {error}")
        if hasattr(error, "m4world_local_env"):
            portable.m4world_local_env = error.m4world_local_env
        return portable


# ------------------------------------------------------------------------------------ main side


class SimulationWorkers:
    """The main process's handle on the worker processes and their shared arrays."""

    def __init__(
        self,
        num_workers: int,
        num_envs: int,
        scenario: Scenario,
        config: EnvConfig,
        model_config: ModelConfig,
        vae_weights: dict[str, np.ndarray],
        chunks_per_step: int,
        torch_threads: int,
    ) -> None:
        check_main_guard()
        self.rows = worker_rows(num_envs, num_workers)
        self.owner = np.repeat(np.arange(num_workers), [hi - lo for lo, hi in self.rows])
        state = config.state_objects if "state" in config.observation_keys else None
        self.shared = SharedArrays.create(shared_array_shapes(model_config, num_envs, chunks_per_step, state))
        ctx = get_context("spawn")
        self.conns: list[Connection] = []
        self.processes = []
        # Each worker's spec (the VAE weights among it) goes through its pipe from a thread once the
        # worker runs, not as the process's argument: multiprocessing writes those while it holds
        # the pipe's other end itself, so a worker that exits before reading them (a script without
        # a main guard) would block that write forever. Only the bounded wait below blocks.
        self._senders: list[threading.Thread] = []
        self._broken: str | None = None
        self._finalize = weakref.finalize(self, _shutdown, self.conns, self.processes, self._senders, self.shared)
        self.wait_s = 0.0  # main's wall seconds waiting for the workers
        try:
            for k, rows in enumerate(self.rows):
                spec = WorkerSpec(
                    k, rows, scenario, config, model_config, vae_weights, self.shared.layout, torch_threads
                )
                ours, theirs = ctx.Pipe()
                process = ctx.Process(target=run_worker, args=(theirs,), name=f"m4world-sim-{k}", daemon=True)
                self.conns.append(ours)
                self.processes.append(process)
                process.start()
                theirs.close()
                sender = threading.Thread(
                    target=_send_quietly, args=(ours, spec), name=f"m4world-sim-{k}-spec", daemon=True
                )
                self._senders.append(sender)
                sender.start()
            deadline = time.monotonic() + START_TIMEOUT_S
            for k in range(num_workers):
                self._receive(k, deadline, starting=True)
        except BaseException:
            self.close()
            raise

    @property
    def slots(self) -> dict[str, np.ndarray]:
        return self.shared.arrays

    def request(self, messages: dict[int, tuple[str, tuple]]) -> dict[int, Any]:
        """Send each worker its (command, args), then collect every reply (they run in parallel).
        A worker's exception is raised here (the lowest sub-env's first) once all have answered."""
        self.check_usable()
        t0 = time.perf_counter()
        for k, message in messages.items():
            try:
                self.conns[k].send(message)
            except (BrokenPipeError, ConnectionResetError, EOFError) as e:
                self._fail(k, f"its pipe closed ({e})")
        replies, errors = {}, []
        deadline = time.monotonic() + REPLY_TIMEOUT_S
        for k in messages:
            try:
                replies[k] = self._receive(k, deadline)
            except SimulationWorkerError:
                raise
            except Exception as e:  # noqa: BLE001 (the worker's error, raised below in sub-env order)
                errors.append((getattr(e, "m4world_sub_env", self.rows[k][0]), e))
        self.wait_s += time.perf_counter() - t0
        if errors:
            raise min(errors, key=lambda item: item[0])[1]
        return replies

    def by_worker(self, indices: Sequence[int]) -> dict[int, list[int]]:
        """Global sub-env ``indices`` grouped by the worker owning them, in order."""
        groups: dict[int, list[int]] = {}
        for i in indices:
            groups.setdefault(int(self.owner[i]), []).append(int(i))
        return groups

    def seconds(self) -> dict[str, float]:
        """Wall seconds of traffic, crops and conditions, summed over the workers (work done on
        every core, not main's waiting)."""
        total: dict[str, float] = {}
        for reply in self.request({k: ("seconds", ()) for k in range(len(self.rows))}).values():
            for key, value in reply.items():
                total[key] = total.get(key, 0.0) + value
        return total

    def close(self) -> None:
        """Stop the workers (joined; killed if they do not stop) and unlink the shared memory."""
        self._broken = self._broken or "the vector env was closed"
        self._finalize()

    def _receive(self, k: int, deadline: float, starting: bool = False) -> Any:
        """Worker ``k``'s reply, waiting until ``deadline`` (``time.monotonic()``) at most and no
        longer than the worker lives."""
        conn, process = self.conns[k], self.processes[k]
        hint = f" while starting ({MAIN_GUARD_HINT})" if starting else ""
        ready = wait([conn, process.sentinel], max(0.0, deadline - time.monotonic()))
        if conn in ready:
            try:
                status, *payload = conn.recv()
            except (EOFError, ConnectionResetError):
                process.join(1.0)
                self._fail(k, f"it exited with code {process.exitcode}{hint}")
            if status == "ok":
                return payload[0]
            error, remote_traceback = payload
            return self._raise_remote(k, error, remote_traceback)
        if process.sentinel in ready or not process.is_alive():
            process.join(1.0)
            self._fail(k, f"it exited with code {process.exitcode}{hint}")
        self._fail(k, f"it did not answer within {START_TIMEOUT_S if starting else REPLY_TIMEOUT_S:.0f} s")

    def _raise_remote(self, k: int, error: Exception, remote_traceback: str) -> None:
        lo, hi = self.rows[k]
        local = getattr(error, "m4world_local_env", None)
        where = f"sub-env {lo + local}" if local is not None else f"simulation worker {k} (sub-envs {lo}..{hi - 1})"
        try:
            tagged = type(error)(f"{where}: {error}")
        except Exception:  # noqa: BLE001 (an exception type that takes other arguments)
            tagged = error
        tagged.m4world_sub_env = lo + (local or 0)
        # The worker's traceback rides along as the cause (exception notes need Python 3.11).
        raise tagged from RemoteTraceback(f"in simulation worker {k}:\n{remote_traceback}")

    def _fail(self, k: int, why: str) -> None:
        lo, hi = self.rows[k]
        self._broken = f"simulation worker {k} (sub-envs {lo}..{hi - 1}) stopped: {why}"
        self._finalize()
        raise SimulationWorkerError(f"{self._broken}; the vector env is closed, make a new one")

    def check_usable(self) -> None:
        if self._broken is not None:
            raise SimulationWorkerError(f"{self._broken}; make a new vector env")


def _send_quietly(conn: Connection, message: Any) -> None:
    """Send ``message`` (a thread's job); a worker gone before reading it is reported by
    :meth:`SimulationWorkers._receive`, which watches the process."""
    with suppress(OSError, ValueError):
        conn.send(message)


def _shutdown(conns: list[Connection], processes: list, senders: list[threading.Thread], shared: SharedArrays) -> None:
    """Ask every worker to stop, join (terminate, kill what stays), unlink the shared memory."""
    # A worker that has not read its spec yet is terminated at once: its pipe takes nothing else.
    sending = [k < len(senders) and senders[k].is_alive() for k in range(len(conns))]
    for conn, busy in zip(conns, sending, strict=True):
        if not busy:
            with suppress(OSError, ValueError):  # already gone
                conn.send(("close", ()))
    for process, busy in zip(processes, sending, strict=True):
        if process.pid is None:  # its start failed
            continue
        process.join(0.0 if busy else JOIN_TIMEOUT_S)
        if process.is_alive():
            process.terminate()
            process.join(JOIN_TIMEOUT_S)
        if process.is_alive():
            process.kill()
            process.join()
    for sender in senders:  # its worker is gone: the send ends
        sender.join(JOIN_TIMEOUT_S)
    for conn in conns:
        conn.close()
    shared.unlink()


# ------------------------------------------------------------------------------- vector env side


@dataclass(frozen=True)
class SubEnvStep:
    """One sub-env's part of a vector step (a restarted one: its first observation, reward 0)."""

    obs: dict[str, np.ndarray]
    reward: float
    terminated: bool
    truncated: bool
    info: dict[str, Any]


class WorkerSubEnv:
    """Stands for sub-env ``index`` of a vector env with workers: forwards the object edits
    (:data:`OBJECT_METHODS`) to its worker; anything else of the sub-env lives in that process."""

    def __init__(self, subenvs: WorkerSubEnvs, index: int) -> None:
        self._subenvs, self.index = subenvs, index

    def insert_object(self, spec: dict[str, Any]) -> str:
        """:meth:`M4WorldEnv.insert_object` in the worker."""
        return self._subenvs.call(self.index, "insert_object", spec)

    def remove_object(self, track_id: str) -> None:
        """:meth:`M4WorldEnv.remove_object` in the worker."""
        self._subenvs.call(self.index, "remove_object", track_id)

    def edit_object(self, track_id: str, **changes: Any) -> None:
        """:meth:`M4WorldEnv.edit_object` in the worker."""
        self._subenvs.call(self.index, "edit_object", track_id, **changes)

    def __getattr__(self, name: str) -> Any:
        raise AttributeError(
            f"sub-env {self.index} runs in a simulation worker process (config.workers > 0): only "
            f"{', '.join(OBJECT_METHODS)} reach it; use workers=0 for direct access to .{name}"
        )


class WorkerSubEnvs:
    """A vector env's sub-envs run by :class:`SimulationWorkers`, its sensors by ``backend``."""

    def __init__(
        self, backend: WorldModelBackend, scenario: Scenario, config: EnvConfig, num_envs: int, frames_per_step: int
    ) -> None:
        import torch

        self.backend, self.n, self.keys = backend, num_envs, config.observation_keys
        wm = backend.wm
        self.workers = SimulationWorkers(
            config.workers,
            num_envs,
            scenario,
            config,
            wm.cfg,
            {k: v.detach().cpu().numpy() for k, v in wm.vae.state_dict().items()},
            frames_per_step // wm.cfg.clip.chunk_frames,
            torch.get_num_threads(),
        )
        self.needs_reset = np.ones(num_envs, dtype=bool)  # no episode yet, or its reset failed
        self.proxies = [WorkerSubEnv(self, i) for i in range(num_envs)]

    def reset(
        self, indices: list[int], seeds: list[int | None], options: dict[str, Any] | None
    ) -> list[tuple[dict[str, np.ndarray], dict[str, Any]]]:
        self.needs_reset[indices] = True
        seed_of = dict(zip(indices, seeds, strict=True))
        groups = self.workers.by_worker(indices)
        replies = self.workers.request(
            {
                k: ("reset", ([i - self.workers.rows[k][0] for i in rows], [seed_of[i] for i in rows], options))
                for k, rows in groups.items()
            }
        )
        reports = {i: r for k, rows in groups.items() for i, r in zip(rows, replies[k], strict=True)}
        first = self._first_observations(indices, [reports[i] for i in indices], options)
        self.needs_reset[indices] = False
        return [(first[i], reports[i].info) for i in indices]

    def step(self, actions: list[Any], restarting: np.ndarray) -> list[SubEnvStep]:
        self.workers.check_usable()
        stale = np.flatnonzero(self.needs_reset & ~restarting)
        if len(stale):
            raise ResetNeeded(
                f"sub-env {stale[0]}: call env.reset() before env.step() "
                "(the episode never started, or the last reset failed)"
            )
        rows = self.workers.rows
        self.workers.request({k: ("check", (actions[lo:hi], restarting[lo:hi])) for k, (lo, hi) in enumerate(rows)})
        replies = self.workers.request({k: ("advance", ()) for k in range(len(rows))})
        reports = [r for k in range(len(rows)) for r in replies[k]]
        active = [i for i in range(self.n) if not restarting[i]]
        block = read_arrays(self.workers.slots, "step.", active)
        chunks = block["ego"].shape[1]
        arrays: list[list[ConditionArrays] | None] = [None] * self.n
        for j, i in enumerate(active):
            arrays[i] = [_arrays_at(block, (j, c)) for c in range(chunks)]
        outs = self.backend.step_arrays(arrays)
        restarted = [i for i in range(self.n) if restarting[i]]
        first = self._first_observations(restarted, [reports[i] for i in restarted], None)
        states = self._states(range(self.n))
        steps = []
        for i, report in enumerate(reports):
            if restarting[i]:
                steps.append(SubEnvStep(first[i], 0.0, False, False, report.info))
            else:
                obs = observation_dict(self.keys, outs[i][-1], states[i])
                steps.append(SubEnvStep(obs, report.reward, report.terminated, report.truncated, report.info))
        return steps

    def call(self, index: int, method: str, *args: Any, **kwargs: Any) -> Any:
        k = int(self.workers.owner[index])
        local = index - self.workers.rows[k][0]
        return self.workers.request({k: ("call", (local, method, args, kwargs))})[k]

    def close(self) -> None:
        self.workers.close()

    def _first_observations(
        self, indices: list[int], reports: list[SubEnvReport], options: dict[str, Any] | None
    ) -> dict[int, dict[str, np.ndarray]]:
        """The first observations of sub-envs whose episodes the workers (re)started: one batched
        reference-model call over the first frames' arrays (from shared memory)."""
        if not indices:
            return {}
        block = read_arrays(self.workers.slots, "first.", indices)
        arrays = [_arrays_at(block, (j,)) for j in range(len(indices))]
        starts = [r.start for r in reports]
        observations = self.backend.start_many(
            indices, [s.frame for s in starts], arrays, options, [s.seed for s in starts]
        )
        states = self._states(indices)
        return {
            i: observation_dict(self.keys, obs, states[j])
            for j, (i, obs) in enumerate(zip(indices, observations, strict=True))
        }

    def _states(self, indices: Sequence[int]) -> list[np.ndarray | None]:
        if "state" not in self.keys:
            return [None] * len(indices)
        return list(self.workers.slots["state"][list(indices)])
