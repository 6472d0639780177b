"""Which precision the DiTs run in on the device at hand.

A checkpoint trained with ``dit.autocast_bf16`` may run its DiTs in bfloat16, but bf16 is only
faster where the hardware multiplies it natively: CUDA GPUs that support it, and CPUs with
AVX512-BF16 or AMX tiles. Elsewhere (AVX2 laptops, AVX512 CPUs without the BF16 extension)
PyTorch emulates bf16 matrix products and they run several times *slower* than float32
(``benchmarks/bench_model.py`` measures both peaks). ``dtype="auto"`` therefore picks bf16 only
where it is fast.
"""

from __future__ import annotations

import torch

DTYPES = ("auto", "float32", "bfloat16")


def cpu_has_native_bf16() -> bool:
    """Whether this CPU multiplies bf16 natively (AVX512-BF16 or AMX), as PyTorch detects it."""
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)


def bf16_is_fast(device: torch.device | str) -> bool:
    """Whether bf16 matrix products on ``device`` run at native speed (faster than float32)."""
    kind = torch.device(device).type
    if kind == "cpu":
        return cpu_has_native_bf16()
    if kind == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    return False


def resolve_bf16(dtype: str, trained_bf16: bool, device: torch.device | str) -> bool:
    """Run the DiTs in bf16? ``dtype``: "auto" (bf16 when the checkpoint was trained with bf16
    autocast *and* the device computes bf16 natively), "float32" or "bfloat16" (forced)."""
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
    if dtype == "auto":
        return trained_bf16 and bf16_is_fast(device)
    return dtype == "bfloat16"
