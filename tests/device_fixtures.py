"""Run the runtime with the model on another device, without that device: the ``meta`` device
stands in for a GPU, and :class:`OnDevice` flags every tensor created off the model's device.

A tensor on ``meta`` has a shape and no data. Torch refuses to mix it with a CPU tensor exactly as
it refuses to mix a CUDA tensor with one (``Tensor on device meta is not on the expected device
cpu!``), so a forgotten ``device=`` surfaces here as it does on a GPU. What a GPU run reads back to
the host (``.cpu()``, ``.numpy()``, ``bool()``, ``.item()``) has no data on ``meta``: :class:`OnDevice`
answers those reads with zeros (``False`` for a truth value), enough for the code to carry on.

:class:`OnDevice` also raises at any tensor factory (``torch.zeros``, ``torch.as_tensor``, ...)
whose result lands off the model's device, naming the line that called it. Allowed: random draws
from a seeded CPU ``torch.Generator`` (the runtime draws noise on the CPU and moves it, so a
seed gives the same noise on every device), the test's own code, and :data:`HOST_SIDE`.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode

FACTORIES = {
    torch.arange,
    torch.as_tensor,
    torch.empty,
    torch.eye,
    torch.from_numpy,
    torch.full,
    torch.linspace,
    torch.logspace,
    torch.normal,
    torch.ones,
    torch.rand,
    torch.randint,
    torch.randn,
    torch.randperm,
    torch.tensor,
    torch.zeros,
}
RANDOM = {torch.normal, torch.rand, torch.randint, torch.randn, torch.randperm}

CHECKED = ("world_model", "m4world_env")  # the packages whose factories are checked

# Genuinely host-side work: (file under the repository root, function) whose CPU tensors are
# either bookkeeping that drives Python control flow or host data moved to the device by its
# consumer in one copy.
HOST_SIDE = {
    ("world_model/model/conditions.py", "collate"),  # numpy condition arrays -> tensors, moved by the model's caller
    ("world_model/student/cache.py", "__init__"),  # per-row frame counts: Python control flow reads them
    ("world_model/student/cache.py", "valid"),  # slot validity from those counts, moved in context()
    ("world_model/student/cache.py", "restart_rows"),  # the restarted row numbers
    ("world_model/student/cache.py", "_rows"),  # row numbers -> folded (B*V) indices
    ("world_model/student/config.py", "times"),  # the denoising schedule, built once per engine
    ("world_model/model/flow.py", "time_grid"),  # the Euler grid, moved by euler_integrate
}

_ROOT = Path(__file__).resolve().parents[1]
_HERE = Path(__file__).resolve()
_TORCH = Path(torch.__file__).resolve().parent


def _caller() -> tuple[Path, str, int]:
    """The first frame outside torch and this module: (file, function, line)."""
    frame = sys._getframe(2)
    while frame is not None:
        path = Path(frame.f_code.co_filename).resolve()
        if path != _HERE and _TORCH not in path.parents:
            return path, frame.f_code.co_name, frame.f_lineno
        frame = frame.f_back
    raise AssertionError("no caller outside torch")


def _host_stand_in(t: torch.Tensor) -> torch.Tensor:
    return torch.zeros(t.shape, dtype=t.dtype)


class OffDeviceTensor(AssertionError):
    """A tensor factory made a tensor off the model's device."""


class OnDevice(TorchFunctionMode):
    """Within it, tensor factories must produce tensors on ``device`` (see the module docstring)."""

    def __init__(self, device: torch.device | str = "meta") -> None:
        super().__init__()
        self.device = torch.device(device)
        self.host_reads = 0  # reads of device data back to the host, answered with zeros

    def _allowed(self, func: object, kwargs: dict) -> tuple[bool, str]:
        path, name, line = _caller()
        where = f"{path.relative_to(_ROOT) if _ROOT in path.parents else path}:{line} ({name})"
        if not any(_ROOT / package in path.parents for package in CHECKED):
            return True, where  # the test's own set-up, third-party code (e.g. module-level constants)
        gen = kwargs.get("generator")
        if func in RANDOM and gen is not None and gen.device.type == "cpu":
            return True, where
        if (path.relative_to(_ROOT).as_posix(), name) in HOST_SIDE:
            return True, where
        return False, where

    def __torch_function__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        kwargs = kwargs or {}
        on_meta = self.device.type == "meta" and bool(args) and isinstance(args[0], torch.Tensor)
        if on_meta and args[0].device.type == "meta":
            t = args[0]
            if func in (torch.Tensor.__bool__,):
                self.host_reads += 1
                return False
            if func in (torch.Tensor.item, torch.Tensor.__int__, torch.Tensor.__index__):
                self.host_reads += 1
                return 0
            if func is torch.Tensor.__float__:
                self.host_reads += 1
                return 0.0
            if func in (torch.Tensor.cpu, torch.Tensor.numpy, torch.Tensor.tolist, torch.Tensor.__array__):
                self.host_reads += 1
                host = _host_stand_in(t)
                if func is torch.Tensor.cpu:
                    return host
                return host.numpy() if func is not torch.Tensor.tolist else host.tolist()
            if func is torch.Tensor.to:
                device, dtype, _, _ = torch._C._nn._parse_to(*args[1:], **kwargs)
                if device is not None and device.type == "cpu":
                    self.host_reads += 1
                    return _host_stand_in(t).to(dtype or t.dtype)
        out = func(*args, **kwargs)
        if func in FACTORIES and isinstance(out, torch.Tensor) and out.device != self.device:
            ok, where = self._allowed(func, kwargs)
            if not ok:
                raise OffDeviceTensor(
                    f"torch.{func.__name__} made a {out.device} tensor at {where} while the model is on {self.device}"
                )
        return out
