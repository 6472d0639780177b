"""split_rows: a batch computed row for row as batches of one, where CPU kernels would differ."""

from dataclasses import replace

import torch
import torch.nn.functional as F

import world_model.model.rows as rows_module
from tests.model_fixtures import perturbed, tiny_conditions
from world_model.model import MultiViewDiT, get_preset
from world_model.model.rows import MIN_CONSISTENT_GEMM_ROWS, split_rows


def _per_row(fn, *batched, rows):
    return torch.cat([fn(*(x.chunk(rows)[i] for x in batched)) for i in range(rows)])


def test_small_linears_and_small_matrix_products_equal_their_rows_alone_bit_for_bit():
    gen = torch.Generator().manual_seed(0)
    w, b = torch.randn(384, 128, generator=gen), torch.randn(384, generator=gen)
    x = torch.randn(8 * 2, 128, generator=gen)  # 8 rollouts of 2 rows: the timestep MLP's shape
    q, k = torch.randn(8, 2, 224, 16, generator=gen), torch.randn(8, 2, 16, 9, generator=gen)
    with split_rows(8):
        lin, prod = F.linear(x, w, b), torch.matmul(q, k)
    assert torch.equal(lin, _per_row(lambda a: F.linear(a, w, b), x, rows=8))
    assert torch.equal(prod, _per_row(torch.matmul, q, k, rows=8))


def test_large_products_run_whole_and_still_equal_their_rows_alone():
    gen = torch.Generator().manual_seed(1)
    w = torch.randn(128, 128, generator=gen)
    x = torch.randn(4 * MIN_CONSISTENT_GEMM_ROWS * 7, 128, generator=gen)
    calls = []

    class Count(torch.overrides.TorchFunctionMode):
        def __torch_function__(self, func, types, args=(), kwargs=None):
            calls.append(func)
            return func(*args, **(kwargs or {}))

    with Count(), split_rows(4):  # the innermost mode sees the calls split_rows makes
        out = F.linear(x, w)
    assert calls.count(F.linear) == 1
    assert torch.equal(out, _per_row(lambda a: F.linear(a, w), x, rows=4))


def test_a_sum_over_the_batch_is_not_cut():
    x = torch.arange(12.0).reshape(6, 2)
    with split_rows(3):
        assert torch.equal(x.sum(dim=0), torch.tensor([30.0, 36.0]))
        assert torch.equal(torch.sum(x, dim=1), torch.tensor([1.0, 5, 9, 13, 17, 21]))


class _Count(torch.overrides.TorchFunctionMode):
    """Counts the calls an inner mode passes on (the blocks' plain calls never reach it)."""

    def __init__(self):
        super().__init__()
        self.calls = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        self.calls += 1
        return func(*args, **(kwargs or {}))


def _two_batched_forwards(frames: int, rows: int = 3):
    """The calls the mode passes on in two alike batched forwards of a tiny DiT, and their outputs."""
    cfg = get_preset("tiny")
    cfg = replace(cfg, dit=replace(cfg.dit, autocast_bf16=False))
    torch.manual_seed(0)
    model = perturbed(MultiViewDiT(cfg), 0).eval()
    cond = tiny_conditions(cfg, frames, batch=rows)
    x = torch.randn(rows, *cfg.latent_shape(frames), generator=torch.Generator().manual_seed(2))
    t = torch.rand(rows, frames, generator=torch.Generator().manual_seed(3))
    counts, outs = [], []
    with torch.no_grad():
        for _ in range(2):
            with _Count() as count, split_rows(rows):
                outs.append(model(x, t, cond))
            counts.append(count.calls)
    return counts, outs


def test_blocks_that_split_nothing_run_without_the_mode_from_their_second_run_on(monkeypatch):
    # The tiny preset's blocks have few tokens a row; with nothing counted small the mode splits
    # nothing in them, as in the default preset's student steps.
    monkeypatch.setattr(rows_module, "MIN_CONSISTENT_GEMM_ROWS", 1)
    counts, (first, second) = _two_batched_forwards(frames=4)
    assert counts[1] < counts[0] / 2  # the blocks' calls no longer pass through the mode
    assert torch.equal(first, second)


def test_blocks_that_split_something_stay_under_the_mode():
    counts, (first, second) = _two_batched_forwards(frames=4)
    assert counts[1] == counts[0]
    assert torch.equal(first, second)
