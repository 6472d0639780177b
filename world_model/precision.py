"""Which precision the DiTs run in on the device at hand.

A checkpoint trained with ``dit.autocast_bf16`` may run its DiTs in bfloat16. Where PyTorch
emulates bf16 (AVX2 laptops, AVX512 CPUs without the BF16 extension) its matrix products run
several times *slower* than float32 (``m4world bench model`` measures both peaks), so
``dtype="auto"`` picks bf16 only where the hardware multiplies it faster than float32: CUDA GPUs
that support it, CPUs with AMX tiles, and CPUs whose AVX512-BF16 is not Intel's. Without AMX,
Intel's AVX512-BF16 multiplies bf16 slower than float32: on a 2-core Xeon with AVX512-BF16 and no
AMX, the bf16 matmul peak was 90 GFLOP/s against float32's 224 (``m4world bench model``), and one
env stepped in 213 ms in float32 against 299 in bf16 (docs/performance.md); at sixteen seeds float32
ranks the agreement report's zoo as well as bf16 (the same note). AMD's AVX512-BF16 is fast: on a
2-core AMD EPYC with it, one env stepped in 93 ms in bf16 against 136 ms in float32 (the same note).
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


def _cpu_probe(name: str) -> bool:
    import torch

    return bool(getattr(torch.cpu, name, lambda: False)())


def cpu_has_amx() -> bool:
    """Whether this CPU has AMX tiles, as PyTorch detects them."""
    return _cpu_probe("_is_amx_tile_supported")


def cpu_has_native_bf16() -> bool:
    """Whether this CPU multiplies bf16 natively (AVX512-BF16 or AMX), as PyTorch detects it."""
    return _cpu_probe("_is_avx512_bf16_supported") or cpu_has_amx()


INTEL = "GenuineIntel"


def cpu_vendor() -> str:
    """The CPU's vendor id as Linux reports it (``INTEL``, "AuthenticAMD"); "" where unknown."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("vendor_id"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def cpu_bf16_is_fast() -> bool:
    """Whether this CPU multiplies bf16 faster than float32: AMX tiles, or AVX512-BF16 not Intel's
    (see the module docstring)."""
    return cpu_has_amx() or (cpu_has_native_bf16() and cpu_vendor() != INTEL)


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
    """Whether ``device`` multiplies bf16 faster than float32 (natively, and not at a lower rate)."""
    import torch

    kind = torch.device(device).type
    if kind == "cpu":
        return cpu_bf16_is_fast()
    if kind == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    return False


def resolve_bf16(dtype: str, trained_bf16: bool, device: torch.device | str) -> bool:
    """Run the DiTs in bf16? ``dtype``: "auto" (bf16 when the checkpoint was trained with bf16
    autocast *and* the device computes bf16 faster than float32), "float32" or "bfloat16" (forced)."""
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
