"""Streaming engine of the causal few-step student (§4.2-§4.3): the ONE denoising loop used by
training rollouts (Self-Forcing, long tuning) and by inference (the gym env).

    engine = StreamingEngine(student, StudentConfig(), generator)
    engine.start(first_latents, first_controls)      # (B, F0, V, C, h, w), F0 frames of controls
    latents = engine.step(next_controls)            # (B, chunk, V, C, h, w), controls of the chunk
    engine.start_rows([3], new_first, new_controls)  # reset one rollout, the others continue

Per chunk: ``StreamingConfig.denoising_steps`` student evaluations (:func:`few_step_sample`), then one
forward of the clean chunk at t = 1 that writes its keys/values into the :class:`KVCache`
(rolling window of ``clip.context_frames`` frames + optional sinks).

Latent context refresh (§4.2, ``context_refresh`` of ``StudentConfig.streaming``): the previous
chunk's last clean frame latent is fed again, at t = 1, in front of the noisy chunk at every
denoising step; the two form one attention block, so its keys/values depend on the chunk noise
and are recomputed each step; the cache's copy of that frame is left out of the context.
``refresh_steps`` limits the refresh to some denoising steps (the others attend to the cache's
copy, as without refresh): a cheaper middle point between the two, measured in docs/MODEL_CARD.md.

Time positions: one RoPE frame counter is shared by the batch. A row restarted with
:meth:`start_rows` places its first frames just before the next chunk; RoPE only sees relative
offsets, so the row is exactly a fresh rollout shifted in time. Its stale slots are masked.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import fields

import torch

from world_model.model.attention import KV
from world_model.model.conditions import ConditionArrays, Conditions
from world_model.model.dit import MultiViewDiT
from world_model.model.flow import NoiseSource, gaussian, interpolate, predict_x0
from world_model.model.tokens import ControlTokens
from world_model.streaming import REFRESH_EVERY_STEP
from world_model.student.cache import KVCache
from world_model.student.config import StudentConfig, check_student

X0Fn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # (x_t, t) -> x0 prediction


def few_step_sample(
    x0_fn: X0Fn,
    noise: torch.Tensor,
    times: torch.Tensor,
    renoise: str = "fresh",
    exit_step: int | None = None,
    grad: bool = False,
    generator: NoiseSource = None,
) -> torch.Tensor:
    """The student's few-step sampler: x0 = G(x_t, t) at each time, re-noised to the next time.

    ``times`` (K,) increasing, ``times[0]`` = 0 (pure noise). Stops at ``exit_step`` (default the
    last) and returns that step's x0-prediction; only that step is evaluated with autograd when
    ``grad`` (Self-Forcing's memory-aware backward). ``t`` passed to ``x0_fn`` is (B,).
    """
    last = len(times) - 1 if exit_step is None else exit_step
    if not 0 <= last < len(times):
        raise ValueError(f"exit_step must be in [0, {len(times) - 1}], got {exit_step}")
    b = noise.shape[0]
    x = noise
    for k in range(last + 1):
        t = times[k].expand(b).to(noise.device)
        with torch.set_grad_enabled(grad and k == last):
            x0 = x0_fn(x, t)
        if k == last:
            return x0
        t_next = times[k + 1].expand(b).to(noise.device)
        if renoise == "fresh":
            eps = gaussian(x.shape, generator, x.device)
        else:  # the noise the current sample implies: deterministic, DDIM-like
            tb = t.reshape(b, *[1] * (x.ndim - 1))
            eps = (x - tb * x0) / (1.0 - tb)
        x = interpolate(x0, eps, t_next)
    raise AssertionError("unreachable")


def cat_frames(a: Conditions, b: Conditions) -> Conditions:
    """Conditions of a's frames followed by b's (per-sequence fields taken from b)."""
    return Conditions(
        **{
            f.name: torch.cat([getattr(a, f.name), getattr(b, f.name)], dim=1)
            if f.name in ConditionArrays.TIME_FIELDS
            else getattr(b, f.name)
            for f in fields(Conditions)
        }
    )


def set_rows(cond: Conditions, rows: torch.Tensor, new: Conditions) -> Conditions:
    """A copy of ``cond`` with batch ``rows`` replaced by ``new`` (same frame count)."""

    def put(name: str, value: torch.Tensor) -> torch.Tensor:
        out = value.clone()
        out[rows] = getattr(new, name).to(value.device, value.dtype)
        return out

    return cond.apply(put)


class StreamingEngine:
    """Causal chunk-by-chunk generation with an explicit KV cache (see the module docstring)."""

    def __init__(
        self,
        model: MultiViewDiT,
        student: StudentConfig | None = None,
        generator: NoiseSource = None,
    ) -> None:
        self.model = model
        self.cfg = model.cfg
        self.scfg = student or StudentConfig()
        check_student(self.cfg, self.scfg)
        self.gen = generator
        self.times = self.scfg.times()
        self.cache: KVCache | None = None
        self.position = 0  # RoPE frame index of the next frame (shared by all rows)
        self.last: torch.Tensor | None = None  # (B, 1, V, C, h, w) last clean frame of each row
        self.last_controls: Conditions | None = None  # its controls (1 frame)

    # -- state --
    @property
    def batch_size(self) -> int:
        return 0 if self.last is None else self.last.shape[0]

    def _device(self) -> torch.device:
        return next(self.model.parameters()).device

    def _check_latents(self, x: torch.Tensor, controls: Conditions, what: str) -> None:
        if x.ndim != 6 or tuple(x.shape[2:]) != self.cfg.latent_shape(1)[1:]:
            raise ValueError(
                f"{what} must be (B, F, V, C, h, w) with (V, C, h, w) = "
                f"{self.cfg.latent_shape(1)[1:]}, got {tuple(x.shape)}"
            )
        if controls.batch_size != x.shape[0] or controls.num_frames != x.shape[1]:
            raise ValueError(
                f"{what}: controls are {controls.batch_size} x {controls.num_frames} frames, "
                f"latents {x.shape[0]} x {x.shape[1]}"
            )
        if x.shape[1] > self.cfg.clip.context_frames:
            raise ValueError(f"{what}: {x.shape[1]} first frames exceed the window {self.cfg.clip.context_frames}")

    @torch.no_grad()
    def _clean_kv(
        self,
        x: torch.Tensor,
        controls: Conditions | ControlTokens,
        offset: int,
        context: list[KV] | None = None,
        valid: torch.Tensor | None = None,
    ) -> list[KV]:
        """K/V of clean frames x (one attention block) at RoPE offset ``offset``."""
        t = torch.ones(x.shape[:2], device=x.device)
        _, kvs = self.model(
            x,
            t,
            controls,
            frame_offset=offset,
            kv_context=context,
            return_kv=True,
            context_valid=valid,
            context_only_frames=x.shape[1],  # a K/V pass: no velocity wanted
        )
        return kvs

    def start(self, first_latents: torch.Tensor, controls: Conditions) -> None:
        """Begin B rollouts from clean first frames (B, F0, V, C, h, w) with their controls."""
        self._check_latents(first_latents, controls, "first_latents")
        dev = self._device()
        x, controls = first_latents.to(dev).float(), controls.to(dev)
        b, f0 = x.shape[:2]
        self.position = f0
        self.last, self.last_controls = x[:, -1:].clone(), controls.frames(f0 - 1, f0)
        c = self.cfg
        sink = self.scfg.streaming.sink_frames
        self.cache = KVCache(b, c.sensors.num_views, c.tokens_per_frame, c.clip.context_frames, sink)
        self.cache.append(self._clean_kv(x, controls, 0), f0)

    def start_rows(self, rows: Sequence[int], first_latents: torch.Tensor, controls: Conditions) -> None:
        """Restart rollouts ``rows`` from new first frames (R, F0, ...); the other rows continue."""
        if self.last is None:
            raise RuntimeError("start the batch with start() before restarting rows")
        self._check_latents(first_latents, controls, "first_latents")
        rows = [int(r) for r in rows]
        if len(rows) != first_latents.shape[0] or len(set(rows)) != len(rows):
            raise ValueError(f"rows {rows} must be distinct, one per first_latents sample")
        if rows and (min(rows) < 0 or max(rows) >= self.batch_size):
            raise ValueError(f"rows must be in [0, {self.batch_size}), got {rows}")
        f0 = first_latents.shape[1]
        if f0 > self.position:
            raise ValueError(f"{f0} first frames cannot precede frame position {self.position}")
        dev = self._device()
        x, controls = first_latents.to(dev).float(), controls.to(dev)
        self.cache.restart_rows(rows, self._clean_kv(x, controls, self.position - f0), f0)
        r = torch.as_tensor(rows, dtype=torch.long, device=dev)
        self.last = self.last.clone()
        self.last[r] = x[:, -1:]
        self.last_controls = set_rows(self.last_controls, r, controls.frames(f0 - 1, f0))

    def snapshot(self) -> dict:
        """The rollout state, cheaply: the cache never modifies its tensors in place, so holding
        references is enough. :meth:`restore` rewinds to it (e.g. to draw extra samples from the
        same context for the DMD critic without advancing the rollout)."""
        state = {k: getattr(self, k) for k in ("position", "last", "last_controls")}
        if self.cache is not None:
            state["cache"] = (self.cache.layers, self.cache.count)
        return state

    def restore(self, state: dict) -> None:
        for k, v in state.items():
            if k == "cache":
                self.cache.layers, self.cache.count = v
            else:
                setattr(self, k, v)

    # -- one chunk --
    def chunk_x0_fn(self, controls: Conditions) -> X0Fn:
        """x0-prediction of the next chunk given the current context: (x_t, t (B,)) -> x0. With
        ``StreamingConfig.refresh_steps`` other than every step all rows share one time (the step is read from it)."""
        return self._chunk(controls)[0]

    def _chunk(self, controls: Conditions) -> tuple[X0Fn, ControlTokens]:
        """:meth:`chunk_x0_fn` and the chunk's own control tokens for its commit."""
        m, c = self.model, self.cfg.clip.chunk_frames
        streaming = self.scfg.streaming
        if streaming.context_refresh:
            ctx, valid = self.cache.context(exclude_newest=True)
            tokens = m.tokenize(cat_frames(self.last_controls, controls))

            def refreshed(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
                tt = torch.cat([torch.ones_like(t)[:, None], t[:, None].expand(-1, c)], dim=1)
                v = m(
                    torch.cat([self.last, x], dim=1),
                    tt,
                    tokens,
                    frame_offset=self.position - 1,
                    kv_context=ctx,
                    context_valid=valid,
                    context_only_frames=1,
                )
                return predict_x0(x, v, t)

            chunk_tokens = tokens.frames(1, 1 + c)  # the commit's: no second tokenization
            if streaming.refresh_steps == REFRESH_EVERY_STEP:
                return refreshed, chunk_tokens
            return self._partly_refreshed(refreshed, self._cached_fn(chunk_tokens)), chunk_tokens
        tokens = m.tokenize(controls)
        return self._cached_fn(tokens), tokens

    def _cached_fn(self, tokens: ControlTokens) -> X0Fn:
        """x0-prediction of the next chunk attending to the whole cache (no context refresh)."""
        ctx, valid = self.cache.context()

        def cached(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            v = self.model(x, t, tokens, frame_offset=self.position, kv_context=ctx, context_valid=valid)
            return predict_x0(x, v, t)

        return cached

    def _partly_refreshed(self, refreshed: X0Fn, cached: X0Fn) -> X0Fn:
        """``refreshed`` at the denoising times of ``StreamingConfig.refresh_steps``, ``cached`` at the
        others. The step is read from ``t`` (shared by the batch, as :func:`few_step_sample` passes
        it); a time off the schedule refreshes."""
        refresh = self.scfg.streaming.resolved_refresh_steps()
        skip = self.times[[k for k in range(len(self.times)) if k not in refresh]]

        def partly(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            if bool((t != t[0]).any()):
                raise ValueError("with refresh_steps every row of a chunk must be at the same denoising time")
            return cached(x, t) if bool((skip == t[0].detach().cpu()).any()) else refreshed(x, t)

        return partly

    def step(
        self,
        controls: Conditions,
        noise: torch.Tensor | None = None,
        *,
        exit_step: int | None = None,
        grad: bool = False,
    ) -> torch.Tensor:
        """Generate the next chunk (B, chunk_frames, V, C, h, w) for the chunk's ``controls``:
        :meth:`denoise`, then :meth:`commit` it.

        ``exit_step``/``grad``: Self-Forcing training (see :func:`few_step_sample`); the returned
        latents then carry the exit step's graph, while the cache is written from a detached copy.
        """
        x0, tokens = self.denoise(controls, noise, exit_step=exit_step, grad=grad)
        self.commit(x0.detach(), controls, tokens)
        return x0

    def denoise(
        self,
        controls: Conditions,
        noise: torch.Tensor | None = None,
        *,
        exit_step: int | None = None,
        grad: bool = False,
    ) -> tuple[torch.Tensor, ControlTokens]:
        """The next chunk's latents and its control tokens, the cache left as it is: :meth:`step`
        without the :meth:`commit`, which must follow before the next chunk (a caller may decode
        the latents meanwhile)."""
        if self.last is None:
            raise RuntimeError("call start() before step()")
        c = self.cfg.clip.chunk_frames
        if controls.batch_size != self.batch_size or controls.num_frames != c:
            raise ValueError(
                f"controls must be {self.batch_size} rows x {c} frames (one chunk), "
                f"got {controls.batch_size} x {controls.num_frames}"
            )
        dev = self._device()
        controls = controls.to(dev)
        shape = (self.batch_size, *self.cfg.latent_shape(c))
        if noise is None:
            noise = gaussian(shape, self.gen, dev)
        elif tuple(noise.shape) != shape:
            raise ValueError(f"noise must be {shape}, got {tuple(noise.shape)}")
        with torch.set_grad_enabled(grad and torch.is_grad_enabled()):  # control tokens: graph only if trained
            x0_fn, tokens = self._chunk(controls)
        x0 = few_step_sample(x0_fn, noise.to(dev), self.times, self.scfg.renoise, exit_step, grad, self.gen)
        return x0, tokens

    def commit(self, latents: torch.Tensor, controls: Conditions, tokens: ControlTokens | None = None) -> None:
        """Append clean chunk latents (B, chunk, ...) to the context: re-run at t = 1 into the cache.
        ``tokens``: the chunk's control tokens when already computed (by :meth:`step`).

        Also the teacher-forcing entry point: commit ground-truth latents instead of samples.
        """
        c = latents.shape[1]
        latents, controls = latents.detach().float(), controls.to(latents.device)
        ctx, valid = self.cache.context()
        kv = self._clean_kv(latents, controls if tokens is None else tokens, self.position, ctx, valid)
        self.cache.append(kv, c)
        self.position += c
        self.last, self.last_controls = latents[:, -1:], controls.frames(c - 1, c)
