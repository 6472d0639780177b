"""Which precision the DiTs run in on the device at hand.

A checkpoint trained with ``dit.autocast_bf16`` may run its DiTs in bfloat16. Where PyTorch
emulates bf16 (AVX2 laptops, AVX512 CPUs without the BF16 extension) its matrix products run
several times *slower* than float32 (``m4world bench model`` measures both peaks), so
``dtype="auto"`` picks bf16 only where the hardware multiplies it natively: CUDA GPUs that support
it, and CPUs with AVX512-BF16 or AMX tiles. Native is not always faster: on a Xeon with AVX512-BF16
but no AMX, ``m4world bench model`` measured a matmul peak of 90 GFLOP/s in bf16 against 224 in
float32, and one env stepped faster in float32 (docs/performance.md). "auto" keeps bf16 there, the
precision the shipped checkpoint's headline figures are measured in; at sixteen seeds float32 ranks
the agreement report's zoo as well (docs/experiments.md), so ``dtype="float32"`` is the faster
choice on such a CPU.
Training stages resolve the same choice (``StageRuntime(dtype="auto")``) through
:func:`dit_precision`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from contextvars import ContextVar
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

# Import-light (torch only inside the hardware probes): the env config and the CLI parsers use
# DTYPES and check_dtype without loading torch.
DTYPES = ("auto", "float32", "bfloat16")


def check_dtype(dtype: str) -> None:
    """Refuse a dtype option that is not one of :data:`DTYPES`, naming it."""
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")


def cpu_has_native_bf16() -> bool:
    """Whether this CPU multiplies bf16 natively (AVX512-BF16 or AMX), as PyTorch detects it."""
    import torch

    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)


def resolve_device(name: str | torch.device) -> torch.device:
    """A device option as torch sees it: "auto" (the first CUDA device when torch sees one, else
    the CPU), "cpu", "cuda", "cuda:N", or any other device torch knows. Raises ``ValueError``
    naming the option when torch does not know it or when the CUDA device asked for is missing."""
    import torch

    if str(name) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"device must be auto, cpu, cuda or cuda:N, got {name!r} ({e})") from e
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r} asked for, but this torch build sees no CUDA device")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"device {name!r} asked for, but torch sees {torch.cuda.device_count()} CUDA device(s)")
    return device


def bf16_is_fast(device: torch.device | str) -> bool:
    """Whether ``device`` multiplies bf16 natively (not emulated, which is several times slower than
    float32)."""
    import torch

    kind = torch.device(device).type
    if kind == "cpu":
        return cpu_has_native_bf16()
    if kind == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    return False


def resolve_bf16(dtype: str, trained_bf16: bool, device: torch.device | str) -> bool:
    """Run the DiTs in bf16? ``dtype``: "auto" (bf16 when the checkpoint was trained with bf16
    autocast *and* the device computes bf16 natively), "float32" or "bfloat16" (forced)."""
    check_dtype(dtype)
    if dtype == "auto":
        return trained_bf16 and bf16_is_fast(device)
    return dtype == "bfloat16"


# A DiT built inside :func:`dit_precision` takes its autocast from there instead of its config.
# Scoped to model construction (a context variable, restored on exit): a run-time choice that never
# changes a checkpoint's config, so runs resumed on another machine and their exports stay the same.
_built_bf16: ContextVar[bool | None] = ContextVar("dit_autocast_bf16", default=None)


@contextmanager
def dit_precision(bf16: bool | None) -> Iterator[None]:
    """DiTs constructed inside run bf16 autocast iff ``bf16`` (None: as their ``dit.autocast_bf16``
    says). Training wraps each stage in it (``StageRuntime(dtype=...)``): its models hold float32
    weights, so either choice is valid for them."""
    token = _built_bf16.set(bf16)
    try:
        yield
    finally:
        _built_bf16.reset(token)


def built_autocast_bf16(configured: bool) -> bool:
    """The bf16 autocast of a DiT constructed now whose config says ``configured``."""
    override = _built_bf16.get()
    return configured if override is None else override


def bf16_autocast(device_type: str, enabled: bool) -> AbstractContextManager[None]:
    """bf16 autocast on ``device_type`` when ``enabled``; a no-op context otherwise, so a model in
    float32 runs on any device, also one without autocast support."""
    import torch

    return torch.autocast(device_type, dtype=torch.bfloat16) if enabled else nullcontext()
