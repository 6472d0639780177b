"""m4world bench digests: the env's observations hashed per scenario, seed, step and key, and a
later run compared with an earlier one key by key."""

import json

from m4world_env.bench.digests import main


def test_a_run_matches_itself_and_names_each_observation_that_changed(tmp_path, capsys):
    run = ["--backend", "procedural", "--scenarios", "merge_cut_in", "--seeds", "0", "--steps", "1"]
    before, after = tmp_path / "before.json", tmp_path / "after.json"
    assert main([*run, "--out", str(before)]) == 0
    digests = json.loads(before.read_text())
    assert sorted(digests) == [f"merge_cut_in/0/{step}/{key}" for step in (0, 1) for key in ("cameras", "lidar")]
    assert main([*run, "--out", str(after), "--compare", str(before)]) == 0
    assert "4 of 4 observations identical" in capsys.readouterr().out
    before.write_text(json.dumps({**digests, "merge_cut_in/0/1/lidar": "0" * 16}))
    assert main([*run, "--out", str(after), "--compare", str(before)]) == 1
    printed = capsys.readouterr().out
    assert "differs: merge_cut_in/0/1/lidar" in printed and "3 of 4 observations identical" in printed
