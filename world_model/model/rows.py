"""Row-independent batched computation on CPU: a batch of B rollouts computes, row for row,
exactly what B batch-of-one calls compute.

On CPU, oneDNN and MKL choose kernels, blockings and reduction splits by problem size: a linear
layer over B * M rows, a batched matmul over B * H matrices or a per-sample sum over a batch is
not bitwise the same, per row, as the same op over M rows (measured with
``m4world bench row_independence``: small-M linears of the timestep and ego MLPs, the cross-
attention's matmuls, the decoder's convolutions and group norms, up to ~1e-6 apart per call, which
a rollout amplifies to 1e-5 m of LiDAR and flipped returns within a few steps). Inside
:func:`split_rows` those ops run once per row block, with the very shapes a single rollout's call
has; every other op (elementwise, softmax, norms over the last dim) is row-independent as it is.

Large products are row-independent as they are, and run whole (splitting them cost a third of a
vector step): a linear whose row blocks have at least :data:`MIN_CONSISTENT_GEMM_ROWS` rows, and a
batched product of matrices with at least that many rows and columns (each matrix is multiplied
alone, by a kernel chosen alike for one block and for all); so do reductions over the last dim
alone (the QK-norm's: each vector is reduced by itself). ``m4world bench row_independence
--no-split`` shows which ops differ; ``tests/test_vector_equality.py`` holds a vector env's rows
to its single envs' bit for bit.

The interception has a cost of its own: the DiT's blocks make thousands of calls a forward,
nearly all passed through whole (an 8-env vector step 10% slower than unsplit with every call
through the mode, 4% with the blocks run plainly; ``m4world bench row_independence --rows 8 --time
4``). :func:`whole_if_split_free` runs the blocks without the mode once a run of the same shapes
split nothing: the mode decides from operand shapes alone, so the same shapes split nothing again.

The tensors of a batched forward are laid out row-major: dim 0 is ``B * k`` with each rollout's
``k`` entries contiguous (``(B, ...)``, ``(B * V, ...)``, ``(B * T, ...)``), so a call's operands
are cut along dim 0 into ``B`` equal blocks. Operands whose dim 0 is not a multiple of ``B``
(weights, shared tables) are passed whole.
"""

from __future__ import annotations

import weakref
from collections.abc import Hashable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

import torch
import torch.nn.functional as F
from torch.overrides import TorchFunctionMode

# Ops whose per-row result depends on the batch they are computed in (CPU kernels chosen by
# shape, reductions split by shape and thread).
ROW_DEPENDENT_OPS = frozenset(
    {
        F.linear,
        torch.matmul,
        torch.Tensor.matmul,
        torch.Tensor.__matmul__,
        torch.bmm,
        torch.baddbmm,
        F.conv2d,
        F.conv_transpose2d,
        F.group_norm,
        torch.sum,
        torch.Tensor.sum,
        torch.linalg.vector_norm,
    }
)


# Fewer rows (or columns) a block than this, and a CPU GEMM may take another kernel for the block
# alone than for the whole batch. Measured in float32: linears of 1-3 rows a rollout differ by
# ~1e-6, and so do products of 224 x 16 by 16 x 9 matrices (cross-attention to 9 tokens); bf16
# differed at no size. Self-attention and the DiT's linears (hundreds of tokens a rollout) run whole.
MIN_CONSISTENT_GEMM_ROWS = 32

# Ops whose operands after the first are all batched alike (matrices per row); for the others
# only the first operand is (a linear's weight or a convolution's kernel is shared).
_ALL_BATCHED = frozenset({torch.matmul, torch.Tensor.matmul, torch.Tensor.__matmul__, torch.bmm, torch.baddbmm})
_REDUCTIONS = {torch.sum: 1, torch.Tensor.sum: 1, torch.linalg.vector_norm: 2}  # position of ``dim``


class _SplitRows(TorchFunctionMode):
    def __init__(self, rows: int) -> None:
        super().__init__()
        self.rows = rows
        self.splits = 0  # calls cut into row blocks so far

    def __torch_function__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204 (torch's protocol)
        kwargs = kwargs or {}
        if func not in ROW_DEPENDENT_OPS or not args or not isinstance(args[0], torch.Tensor):
            return func(*args, **kwargs)
        first, b = args[0], self.rows
        n = first.shape[0] if first.ndim else 0
        if first.device.type != "cpu" or n == 0 or first.numel() == 0 or n % b or _reduces_dim0(func, args, kwargs):
            return func(*args, **kwargs)
        if _reduces_last_dim_only(func, args, kwargs):
            return func(*args, **kwargs)
        batched = [
            i == 0 or (func in _ALL_BATCHED and isinstance(a, torch.Tensor) and a.ndim >= 3 and a.shape[0] == n)
            for i, a in enumerate(args)
        ]
        matrices = func in _ALL_BATCHED and first.ndim >= 3 and args[1].ndim >= 3
        large = matrices and min(first.shape[-2], args[1].shape[-1]) >= MIN_CONSISTENT_GEMM_ROWS
        if matrices and (large or not all(batched[1:])):
            return func(*args, **kwargs)  # broadcast, or products of large matrices, each alone
        if func is F.linear or (func in _ALL_BATCHED and args[1].ndim < 3):  # one GEMM over every row of ``first``
            rows_per_block = first.numel() // max(1, first.shape[-1]) // b
            if rows_per_block >= MIN_CONSISTENT_GEMM_ROWS:
                return func(*args, **kwargs)
        self.splits += 1
        parts = [list(a.chunk(b)) if cut else [a] * b for a, cut in zip(args, batched, strict=True)]
        return torch.cat([func(*(p[i] for p in parts), **kwargs) for i in range(b)])


# The mode of the innermost split_rows of this thread (torch's mode stack is per thread too).
_ACTIVE: ContextVar[_SplitRows | None] = ContextVar("split_rows", default=None)
# Per owner (a module), the (rows, key) pairs whose stretch split nothing under the mode.
_SPLIT_FREE: weakref.WeakKeyDictionary[object, set[Hashable]] = weakref.WeakKeyDictionary()


def _reduced_dims(func: object, args: tuple, kwargs: dict) -> tuple[int, ...] | None:
    """The dims a reduction of :data:`_REDUCTIONS` reduces, each in [0, ndim); () when it reduces
    everything; None for any other op."""
    if func not in _REDUCTIONS:
        return None
    pos = _REDUCTIONS[func]
    dim = kwargs.get("dim", args[pos] if len(args) > pos else None)
    if dim is None:
        return ()
    ndim = args[0].ndim
    return tuple(d % ndim for d in ((dim,) if isinstance(dim, int) else dim))


def _reduces_dim0(func: object, args: tuple, kwargs: dict) -> bool:
    """A reduction over dim 0 (or over everything) mixes the rows: it cannot be cut."""
    dims = _reduced_dims(func, args, kwargs)
    return dims is not None and (not dims or 0 in dims)


def _reduces_last_dim_only(func: object, args: tuple, kwargs: dict) -> bool:
    """A reduction over the last dim alone: each row of every vector is reduced by itself."""
    return _reduced_dims(func, args, kwargs) == (args[0].ndim - 1,)


@contextmanager
def split_rows(rows: int) -> Iterator[None]:
    """Within the block, CPU ops of :data:`ROW_DEPENDENT_OPS` run once per row of a ``rows``-row
    batch (see the module docstring); ``rows`` <= 1 changes nothing."""
    if rows <= 1:
        yield
        return
    mode = _SplitRows(rows)
    token = _ACTIVE.set(mode)
    try:
        with mode:
            yield
    finally:
        _ACTIVE.reset(token)


@contextmanager
def whole_if_split_free(owner: object, key: Hashable) -> Iterator[None]:
    """Inside :func:`split_rows`, the block's ops run as plain calls, without the mode, when an
    earlier run of ``owner``'s block with the same ``key`` split none of them; a run that split
    something stays under the mode every time. ``key`` must determine the shape of every operand
    the block hands to :data:`ROW_DEPENDENT_OPS` (the mode's decisions depend on nothing else).
    Plain calls hide the block's ops from every other torch-function mode too."""
    mode = _ACTIVE.get()
    if mode is None:
        yield
        return
    seen = _SPLIT_FREE.setdefault(owner, set())
    if (mode.rows, key) in seen:
        with torch._C.DisableTorchFunction():
            yield
        return
    before = mode.splits
    yield
    if mode.splits == before:
        seen.add((mode.rows, key))
