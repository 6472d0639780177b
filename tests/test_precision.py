"""The DiTs' precision: "auto" runs bf16 only where the device multiplies it faster than float32."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from tests.model_fixtures import perturbed, tiny_conditions
from world_model import precision
from world_model.bundle import save_bundle
from world_model.model import MultiViewDiT, get_preset
from world_model.model.reference import reference_model_config
from world_model.model.vae import SensorVAE
from world_model.precision import bf16_is_fast, resolve_bf16
from world_model.rollout.runtime import load_world_model


def test_forced_dtypes_ignore_the_hardware(monkeypatch):
    for native in (False, True):
        monkeypatch.setattr(precision, "cpu_bf16_is_fast", lambda native=native: native)
        for trained in (False, True):
            assert resolve_bf16("bfloat16", trained, "cpu") is True
            assert resolve_bf16("float32", trained, "cpu") is False


@pytest.mark.parametrize(
    ("amx", "avx512_bf16", "vendor", "fast"),
    [
        (True, True, precision.INTEL, True),
        (False, True, precision.INTEL, False),  # slower than float32 there (the module docstring)
        (False, True, "AuthenticAMD", True),
        (False, True, "", True),
        (False, False, "AuthenticAMD", False),  # emulated
        (False, False, precision.INTEL, False),
    ],
)
def test_a_cpu_runs_bf16_with_amx_or_avx512_bf16_not_intels(monkeypatch, amx, avx512_bf16, vendor, fast):
    probes = {"_is_amx_tile_supported": amx, "_is_avx512_bf16_supported": avx512_bf16}
    for name, value in probes.items():
        monkeypatch.setattr(torch.cpu, name, lambda value=value: value, raising=False)
    monkeypatch.setattr(precision, "cpu_vendor", lambda: vendor)
    assert precision.cpu_has_native_bf16() is (amx or avx512_bf16)
    assert bf16_is_fast("cpu") is fast


def test_the_cpu_vendor_is_read_from_linux():
    vendor = precision.cpu_vendor()
    assert isinstance(vendor, str)
    try:
        with open("/proc/cpuinfo") as info:
            assert vendor in info.read()
    except OSError:
        assert vendor == ""


def test_auto_needs_a_bf16_checkpoint_and_fast_bf16(monkeypatch):
    for native in (False, True):
        monkeypatch.setattr(precision, "cpu_bf16_is_fast", lambda native=native: native)
        assert bf16_is_fast("cpu") is native
        assert resolve_bf16("auto", True, "cpu") is native
        assert resolve_bf16("auto", False, "cpu") is False
    assert bf16_is_fast("meta") is False


def test_unknown_dtype_is_refused_by_name():
    with pytest.raises(ValueError, match="float16"):
        resolve_bf16("float16", True, "cpu")


@pytest.fixture(scope="module")
def bf16_trained_bundle(tmp_path_factory):
    """A tiny untrained bundle whose config says it was trained with bf16 autocast."""
    cfg = get_preset("tiny")
    cfg = replace(cfg, dit=replace(cfg.dit, autocast_bf16=True))
    student_cfg, ref_cfg = cfg.for_student(), reference_model_config(cfg)
    torch.manual_seed(0)
    parts = {
        "vae": SensorVAE(cfg).state_dict(),
        "student": MultiViewDiT(student_cfg).state_dict(),
        "reference": MultiViewDiT(ref_cfg).state_dict(),
    }
    out = tmp_path_factory.mktemp("bundle") / "bf16"
    return save_bundle(
        out,
        student_cfg.to_dict(),
        parts,
        stages={k: "untrained" for k in parts},
        component_configs={"reference": ref_cfg.to_dict()},
    )


@pytest.mark.parametrize("native", [False, True])
def test_auto_loads_bf16_weights_only_where_bf16_is_fast(monkeypatch, bf16_trained_bundle, native):
    monkeypatch.setattr(precision, "cpu_bf16_is_fast", lambda: native)
    wm = load_world_model(bf16_trained_bundle, dtype="auto")
    want = torch.bfloat16 if native else torch.float32
    for dit in (wm.student, wm.reference):
        assert next(dit.parameters()).dtype == want
        assert dit.cfg.dit.autocast_bf16 is native
    assert wm.cfg.dit.autocast_bf16 is native  # the camera decoder follows the DiTs
    with precision.dit_precision(not native):  # a training context around the load changes nothing
        inside = load_world_model(bf16_trained_bundle, dtype="auto")
    assert inside.student.autocast_bf16 is native and next(inside.student.parameters()).dtype == want


def _forward(model: MultiViewDiT) -> torch.Tensor:
    cfg = model.cfg
    x = torch.randn(2, *cfg.latent_shape(2), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        return model(x, torch.full((2,), 0.5), tiny_conditions(cfg, 2, batch=2))


def test_dit_precision_sets_the_autocast_of_dits_built_inside():
    cfg = get_preset("tiny")
    bf16_cfg = replace(cfg, dit=replace(cfg.dit, autocast_bf16=True))
    torch.manual_seed(0)
    fp32_model = perturbed(MultiViewDiT(cfg))  # zero-initialized heads would hide any rounding
    with precision.dit_precision(False):
        forced_fp32 = MultiViewDiT(bf16_cfg).eval()
        with precision.dit_precision(None):  # None: the config decides
            assert MultiViewDiT(bf16_cfg).autocast_bf16 is True
        assert MultiViewDiT(bf16_cfg).autocast_bf16 is False  # restored on exit
    with precision.dit_precision(True):
        forced_bf16 = MultiViewDiT(cfg).eval()
    as_configured = MultiViewDiT(bf16_cfg).eval()  # outside: the config's bf16
    for m in (forced_fp32, forced_bf16, as_configured):
        m.load_state_dict(fp32_model.state_dict())
    assert (forced_fp32.autocast_bf16, forced_bf16.autocast_bf16, as_configured.autocast_bf16) == (False, True, True)
    reference = _forward(fp32_model)
    assert torch.equal(_forward(forced_fp32), reference)  # the same computation as an fp32 config
    assert not torch.equal(_forward(forced_bf16), reference)  # bf16 autocast rounds
    assert torch.equal(_forward(forced_bf16), _forward(as_configured))
