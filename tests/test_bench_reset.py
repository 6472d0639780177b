"""m4world bench reset on an untrained tiny bundle: reset() with and without a scenario's
completion adapter, and the refusal of a scenario that names none."""

import json

import pytest
import yaml

from m4world_env.bench.reset import main
from m4world_env.scenario import SCENARIOS_DIR
from world_model.lora import LoraConfig, add_adapter, base_fingerprint, remove_adapters, save_adapter
from world_model.rollout.runtime import load_world_model


def test_reset_is_timed_with_and_without_the_completion_adapter(tiny_bundle, tmp_path, capsys, monkeypatch):
    from world_model.model.reference import ReferenceGenerator

    completed = []
    complete = ReferenceGenerator.complete_category

    def counting(self, *args, **kwargs):
        completed.append(args[3])  # the category
        return complete(self, *args, **kwargs)

    monkeypatch.setattr(ReferenceGenerator, "complete_category", counting)
    reference = load_world_model(tiny_bundle).reference
    add_adapter(reference, "van_completion", LoraConfig(rank=2))
    adapter = tmp_path / "van_completion"
    train = {"case": "van", "reference_tasks": True}
    save_adapter(
        reference, "van_completion", adapter, LoraConfig(rank=2), base_fingerprint(reference), {"train": train}
    )
    remove_adapters(reference)
    scenario = yaml.safe_load((SCENARIOS_DIR / "merge_cut_in.yaml").read_text())  # a van in the first frame
    path = tmp_path / "van.yaml"
    path.write_text(yaml.safe_dump({**scenario, "adapters": [str(adapter)]}))
    out = tmp_path / "reset.json"
    assert main(["--scenario", str(path), "--checkpoint", str(tiny_bundle), "--rounds", "2", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["completion_adapters"] == [str(adapter)]
    assert all(len(s) == 2 for s in result["per_round_s"].values())
    assert result["ratio"] == result["with_completion_s"] / result["without_completion_s"]
    assert completed == ["van", "van"]  # one completion per timed reset with the adapter, none without
    with pytest.raises(SystemExit):
        main(["--scenario", "merge_cut_in", "--checkpoint", str(tiny_bundle), "--out", str(tmp_path / "none.json")])
    assert "names no completion adapter" in capsys.readouterr().err
