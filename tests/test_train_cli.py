"""One training command line: ``m4world train`` and ``python -m world_model.train`` are the same parser."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _flags(parser: argparse.ArgumentParser) -> dict[str, object]:
    return {s: a.default for a in parser._actions for s in a.option_strings if s not in ("-h", "--help")}


def test_m4world_train_and_the_module_take_the_same_flags_with_the_same_defaults():
    from m4world_env.cli import build_parser as m4world_parser
    from world_model.train.cli import build_parser

    sub = next(a for a in m4world_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert _flags(sub.choices["train"]) == _flags(build_parser())
    assert {"--device", "--compile", "--all", "--ckpt-every", "--case-clips"} <= set(_flags(build_parser()))
    assert not {"--dmd-norm", "--compress-object-weight"} & set(_flags(build_parser()))


def test_building_the_training_parser_does_not_import_torch():
    code = "import sys; from world_model.train.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "False"


def test_a_leading_double_dash_from_torchrun_is_dropped(tmp_path, capsys):
    from world_model.train.cli import main

    assert main(["--", "--stage", "vae", "--data", str(tmp_path), "--run", str(tmp_path / "r"), "--device", "cpu"]) == 2
    assert "is not an m4world dataset" in capsys.readouterr().err  # parsed and run: the error is the data's
