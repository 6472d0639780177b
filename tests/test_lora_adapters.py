"""LoRA adapters: frozen base, exact save/load/unload round trip, base-hash check, name resolution."""

import pytest
import torch
from torch import nn

from tests.model_fixtures import perturbed, tiny_conditions
from world_model.lora import (
    AdapterMismatchError,
    LoraConfig,
    add_adapter,
    apply_adapters,
    base_fingerprint,
    loaded_adapters,
    remove_adapters,
    save_adapter,
)
from world_model.model import MultiViewDiT, get_preset

CFG = get_preset("tiny")
TARGETS = {"q", "k", "v", "o", "fc1", "fc2"}


@pytest.fixture()
def setup():
    torch.manual_seed(0)
    model = perturbed(MultiViewDiT(CFG))
    cond = tiny_conditions(CFG, 2)
    x = torch.randn(1, *CFG.latent_shape(2), generator=torch.Generator().manual_seed(1))
    return model, cond, x, torch.tensor([0.4])


def _train_adapter(model, name, cond, x, t, steps=3):
    params = add_adapter(model, name, LoraConfig(rank=4))
    opt = torch.optim.Adam(params, lr=1e-2)
    for _ in range(steps):
        loss = model(x, t, cond).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return params


def test_fresh_adapter_is_identity_and_only_it_trains(setup):
    model, cond, x, t = setup
    base = {k: v.clone() for k, v in model.state_dict().items()}
    with torch.no_grad():
        y0 = model(x, t, cond)
    params = add_adapter(model, "case", LoraConfig(rank=4))
    with torch.no_grad():
        assert torch.equal(model(x, t, cond), y0)  # lora_B starts at zero
    names = [n for n, p in model.named_parameters() if p.requires_grad]
    assert names and all(".lora_" in n and ".case." in n for n in names) and len(names) == len(params)
    adapted = {n.split(".lora_")[0].rsplit(".", 1)[-1] for n in names}
    assert adapted == TARGETS and all(n.startswith("blocks.") for n in names)  # DiT blocks only
    remove_adapters(model)
    _train_adapter(model, "case", cond, x, t)
    after = {k.replace(".base_layer.", "."): v for k, v in model.state_dict().items() if ".lora_" not in k}
    assert after.keys() == base.keys() and all(torch.equal(after[k], base[k]) for k in base)  # bit-identical
    with torch.no_grad():
        assert not torch.allclose(model(x, t, cond), y0)


def test_save_apply_remove_round_trips_exactly(setup, tmp_path):
    model, cond, x, t = setup
    keys = list(model.state_dict())
    with torch.no_grad():
        y0 = model(x, t, cond)
    fingerprint = base_fingerprint(model)
    _train_adapter(model, "tree_truck", cond, x, t)
    assert base_fingerprint(model) == fingerprint  # the fingerprint ignores adapters
    with torch.no_grad():
        y1 = model(x, t, cond)
    save_adapter(model, "tree_truck", tmp_path / "tree_truck", LoraConfig(rank=4), fingerprint)
    assert remove_adapters(model) == [] and loaded_adapters(model) == []
    assert all(type(m) is nn.Linear for n, m in model.named_modules() if n.endswith((".q", ".fc1")))
    assert list(model.state_dict()) == keys
    with torch.no_grad():
        assert torch.equal(model(x, t, cond), y0)  # unloaded: the base model again, bit for bit
    assert apply_adapters(model, ["tree_truck"], search_dirs=[tmp_path]) == ["tree_truck"]
    assert not any(p.requires_grad for p in model.parameters())  # inference: nothing trains
    with torch.no_grad():
        assert torch.equal(model(x, t, cond), y1)  # loaded: exactly the trained adapter
    remove_adapters(model, ["tree_truck"])
    with torch.no_grad():
        assert torch.equal(model(x, t, cond), y0)


def test_two_adapters_stack_and_unload_one_at_a_time(setup, tmp_path, monkeypatch):
    model, cond, x, t = setup
    fingerprint = base_fingerprint(model)
    for name in ("a", "b"):
        _train_adapter(model, name, cond, x, t)
        save_adapter(model, name, tmp_path / name, LoraConfig(rank=4), fingerprint)
        remove_adapters(model)
    with torch.no_grad():
        y0 = model(x, t, cond)
        apply_adapters(model, [tmp_path / "a"])  # a path
        ya = model(x, t, cond)
        monkeypatch.setenv("M4WORLD_ADAPTERS", str(tmp_path))
        assert apply_adapters(model, ["b"]) == ["a", "b"]  # a name, found through $M4WORLD_ADAPTERS
        yab = model(x, t, cond)
        assert not torch.allclose(yab, ya)
        assert remove_adapters(model, ["b"]) == ["a"]
        torch.testing.assert_close(model(x, t, cond), ya)
        remove_adapters(model)
        assert torch.equal(model(x, t, cond), y0)


def test_adapter_on_another_base_or_missing_gets_clear_errors(setup, tmp_path):
    model, cond, x, t = setup
    _train_adapter(model, "case", cond, x, t)
    save_adapter(model, "case", tmp_path / "case", LoraConfig(rank=4), base_fingerprint(model))
    other = perturbed(MultiViewDiT(CFG), seed=5)
    with pytest.raises(AdapterMismatchError, match="trained on base weights"):
        apply_adapters(other, [tmp_path / "case"])
    assert loaded_adapters(other) == []
    with pytest.raises(FileNotFoundError, match="--stage lora --case nothing"):
        apply_adapters(other, ["nothing"], search_dirs=[tmp_path])
    with pytest.raises(ValueError, match="already loaded"):
        add_adapter(model, "case")
    with pytest.raises(KeyError, match="not loaded"):
        remove_adapters(model, ["zzz"])


def test_fingerprint_is_the_same_for_float32_and_bf16_copies_of_a_base():
    import copy

    from world_model.lora import base_fingerprint
    from world_model.model import MultiViewDiT, get_preset

    torch.manual_seed(0)
    model = MultiViewDiT(get_preset("tiny"))
    rounded = copy.deepcopy(model).to(torch.bfloat16)  # what a bf16 bundle serves
    assert base_fingerprint(model) == base_fingerprint(rounded)
    with torch.no_grad():
        next(rounded.parameters()).add_(1.0)
    assert base_fingerprint(model) != base_fingerprint(rounded)


def test_adapter_info_names_the_category_a_completion_adapter_completes():
    from world_model.lora import AdapterInfo, LoraConfig

    def info(name, train):
        return AdapterInfo(name, "0" * 64, LoraConfig(), {"train": train})

    assert info("renamed", {"case": "bus", "reference_tasks": True}).completes == "bus"
    assert info("bus", {"reference_tasks": True}).completes == "bus"  # recorded before train.case existed
    assert info("bus", {"case": "bus", "reference_tasks": False}).completes is None  # a student/teacher adapter
    assert info("bus", {}).completes is None


def test_only_adapters_switches_for_a_block_and_restores_everything(setup):
    """Inside: exactly the named adapters act (none: the base model), no requires_grad flag moves;
    after, also after an exception: the adapters active before, per layer."""
    from world_model.lora import only_adapters

    model, cond, x, t = setup
    with torch.no_grad():
        base = model(x, t, cond)
    for name in ("a", "b"):
        add_adapter(model, name, LoraConfig(rank=2, target_modules=("fc2",) if name == "b" else ("q",)))
        with torch.no_grad():
            for pname, p in model.named_parameters():
                if f"lora_B.{name}." in pname:
                    p.normal_()
    assert loaded_adapters(model) == ["a", "b"]  # b is not in the first LoRA layer (a q): still listed
    model.blocks[0].attn.q.set_adapter(["a"])  # layers may differ in what is active
    flags = {n: p.requires_grad for n, p in model.named_parameters()}
    with torch.no_grad():
        with only_adapters(model, []):
            assert torch.equal(model(x, t, cond), base)
            assert {n: p.requires_grad for n, p in model.named_parameters()} == flags
        with only_adapters(model, ["b"]):
            only_b = model(x, t, cond)
        remove_adapters(model, ["a"])
        assert torch.equal(model(x, t, cond), only_b)  # the same as b alone
    add_adapter(model, "a", LoraConfig(rank=2, target_modules=("q",)))
    model.blocks[0].attn.q.set_adapter(["a"])
    flags = {n: p.requires_grad for n, p in model.named_parameters()}
    before = {n: list(m.active_adapters) for n, m in model.named_modules() if hasattr(m, "lora_A")}
    with pytest.raises(RuntimeError, match="inside"), only_adapters(model, ["a"]):
        raise RuntimeError("inside")
    assert {n: list(m.active_adapters) for n, m in model.named_modules() if hasattr(m, "lora_A")} == before
    assert {n: p.requires_grad for n, p in model.named_parameters()} == flags
    with pytest.raises(KeyError, match="not loaded"), only_adapters(model, ["c"]):
        pass


def test_an_adapter_free_model_is_inspected_without_importing_peft():
    """peft imports transformers (seconds, ~150 MB): a rollout without adapters never needs it."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "import sys; from torch import nn; from world_model.lora import loaded_adapters; "
        "assert loaded_adapters(nn.Linear(2, 2)) == []; "
        "print(sorted(m for m in ('peft', 'transformers') if m in sys.modules))"
    )
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=root, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]"
