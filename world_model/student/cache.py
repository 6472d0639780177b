"""Explicit rolling KV cache of a causal streaming rollout (one per :class:`StreamingEngine`).

Per DiT block the cache holds the self-attention keys/values (already RoPE-rotated with their
absolute frame index) of committed *clean* frames, for B independent rollouts x V views:

    k, v : (B*V, heads, (S + W) * N, head_dim)      slots = [S sink | W window], N tokens/frame

* The W window slots hold each row's most recent W frames in time order (newest last).
* The S sink slots hold the row's first S frames (StreamingLLM-style attention sink); a sink slot
  is only *valid* once its frame has left the window, so no frame is ever attended twice.
* Validity is a pure function of the per-row frame count, so rows restarted at different times
  (vector envs) simply carry fewer valid slots; :meth:`context` returns a (B, F) validity mask
  only when rows differ and trims slots that no row uses.

Commits never modify tensors in place: every append builds new tensors, so an autograd graph or
an in-flight denoising pass that read the old cache stays valid ("deferred commit"). Tensor
sizes are fixed at the first commit: memory is bounded however long the rollout runs.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from world_model.model.attention import KV


class KVCache:
    def __init__(self, batch: int, views: int, tokens_per_frame: int, window: int, sink: int = 0) -> None:
        if window < 1 or sink < 0:
            raise ValueError(f"the cache needs window >= 1 and sink >= 0, got {window}, {sink}")
        self.batch, self.views, self.n, self.window, self.sink = batch, views, tokens_per_frame, window, sink
        self.layers: list[KV] | None = None
        self.count = torch.zeros(batch, dtype=torch.long)  # frames committed per row

    @property
    def slots(self) -> int:
        return self.sink + self.window

    def valid(self) -> torch.Tensor:
        """(B, S + W) bool: which slots hold a frame each row may attend to."""
        c = self.count[:, None]
        sink = torch.arange(self.sink)[None] < (c - self.window)  # frame i has left the window
        win = torch.arange(self.window)[None] >= (self.window - c)
        return torch.cat([sink, win], dim=1)

    def nbytes(self) -> int:
        return 0 if self.layers is None else sum(k.nbytes + v.nbytes for k, v in self.layers)

    def _rows(self, rows: torch.Tensor) -> torch.Tensor:
        """Batch rows -> indices into the folded (B*V) axis."""
        return (rows[:, None] * self.views + torch.arange(self.views)[None]).reshape(-1)

    def _allocate(self, like: list[KV]) -> None:
        bv, h, _, hd = like[0][0].shape
        if bv != self.batch * self.views:
            raise ValueError(f"K/V batch {bv} != batch {self.batch} x views {self.views}")
        shape = (bv, h, self.slots * self.n, hd)
        self.layers = [(k.new_zeros(shape), v.new_zeros(shape)) for k, v in like]

    def _check(self, kvs: list[KV], frames: int, rows: int) -> None:
        if self.layers is not None and len(kvs) != len(self.layers):
            raise ValueError(f"expected K/V for {len(self.layers)} layers, got {len(kvs)}")
        want = rows * self.views, frames * self.n
        got = kvs[0][0].shape[0], kvs[0][0].shape[2]
        if got != want:
            raise ValueError(f"K/V must be (rows*V, H, frames*N, hd) with {want}, got {tuple(kvs[0][0].shape)}")

    def append(self, kvs: list[KV], frames: int) -> None:
        """Commit ``frames`` new clean frames of every row: per layer (B*V, H, frames*N, hd)."""
        self._check(kvs, frames, self.batch)
        if self.layers is None:
            self._allocate(kvs)
        s, n, w, vv = self.sink * self.n, self.n, self.window * self.n, self.views
        # (row, sink slot, frame of this commit) for rows still filling their sink.
        writes = [
            (r, int(self.count[r]) + f, f)
            for r in range(self.batch)
            for f in range(frames)
            if int(self.count[r]) + f < self.sink
        ]
        out: list[KV] = []
        for (k, v), (nk, nv) in zip(self.layers, kvs, strict=True):
            pair = []
            for old, new in ((k, nk), (v, nv)):
                new = new.detach().to(old.dtype)
                win = torch.cat([old[:, :, s:], new], dim=2)[:, :, -w:]
                sink = old[:, :, :s]
                if writes:
                    sink = sink.clone()
                    for r, slot, f in writes:
                        sink[r * vv : (r + 1) * vv, :, slot * n : (slot + 1) * n] = new[
                            r * vv : (r + 1) * vv, :, f * n : (f + 1) * n
                        ]
                pair.append(torch.cat([sink, win], dim=2) if s else win)
            out.append((pair[0], pair[1]))
        self.layers = out
        self.count = self.count + frames

    def restart_rows(self, rows: Sequence[int], kvs: list[KV], frames: int) -> None:
        """Forget ``rows``' history and commit their first ``frames`` frames (K/V (R*V, H, frames*N, hd)).

        The new frames take the newest window slots (and sink slots), so the rows continue in
        lockstep with the others; their older slots become invalid.
        """
        if self.layers is None:
            raise RuntimeError("restart_rows needs a started cache; start the whole batch first")
        if frames > self.window:
            raise ValueError(f"{frames} first frames do not fit the window of {self.window}")
        r = torch.as_tensor(list(rows), dtype=torch.long)
        self._check(kvs, frames, len(r))
        idx = self._rows(r).to(self.layers[0][0].device)
        n = self.n
        out: list[KV] = []
        for (k, v), (nk, nv) in zip(self.layers, kvs, strict=True):
            pair = []
            for old, new in ((k, nk), (v, nv)):
                new = new.detach().to(old.dtype)
                t = old.clone()
                t[idx, :, t.shape[2] - frames * n :] = new
                for f in range(min(frames, self.sink)):
                    t[idx, :, f * n : (f + 1) * n] = new[:, :, f * n : (f + 1) * n]
                pair.append(t)
            out.append((pair[0], pair[1]))
        self.layers = out
        self.count = self.count.clone()
        self.count[r] = frames

    def context(self, exclude_newest: bool = False) -> tuple[list[KV] | None, torch.Tensor | None]:
        """Per-layer context K/V for the next chunk and its (B, F) validity (None: all valid).

        ``exclude_newest`` leaves out every row's most recent frame (latent context refresh
        recomputes it together with the new chunk instead).
        """
        if self.layers is None:
            return None, None
        valid = self.valid()
        if exclude_newest:
            valid[:, -1] = False
        used = valid.any(dim=0)
        if not bool(used.any()):
            return None, None
        keep = torch.nonzero(used).flatten()
        lo, hi = int(keep[0]), int(keep[-1]) + 1
        n = self.n
        if hi - lo == len(keep):  # contiguous: views, no copy
            layers = [(k[:, :, lo * n : hi * n], v[:, :, lo * n : hi * n]) for k, v in self.layers]
        else:
            tok = (keep[:, None] * n + torch.arange(n)[None]).reshape(-1).to(self.layers[0][0].device)
            layers = [(k.index_select(2, tok), v.index_select(2, tok)) for k, v in self.layers]
        valid = valid[:, keep]
        return layers, None if bool(valid.all()) else valid.to(self.layers[0][0].device)
