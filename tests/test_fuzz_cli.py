"""Property-based fuzzing of the command lines' flags (``m4world``, ``python -m world_model.train``, the
recipe): a malformed value of a count, a seed, a number or an output path ends the command with exit
status 2 and one message naming the flag and the value, before any work: nothing is written and no
command's work function is called (each is replaced by one that fails the test).

Derandomized with the settings of ``tests/test_fuzz.py``; every flag gets its own examples.
"""

from __future__ import annotations

import contextlib
import functools
import io
import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import gymnasium
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import m4world_env.agreement.run
import m4world_env.evalset
import m4world_env.evaluate
import m4world_env.gallery
import m4world_env.recorder
import m4world_env.text_embeddings
import world_model.bundle
import world_model.train.recipe
import world_model.train.stages
from m4world_env import cli as m4world_cli
from world_model.cli_args import MAX_SEED
from world_model.train import cli as train_cli

from .test_fuzz import EXAMPLES, FUZZ

PER_FLAG = settings(FUZZ, max_examples=max(EXAMPLES // 20, 5))

# Each command's work, which a refused flag must never reach (module, attribute).
WORK = [
    (world_model.train.recipe, "record_clips"),
    (world_model.train.stages, "train_stage"),
    (world_model.bundle, "export_bundle"),
    (m4world_env.recorder, "record"),
    (m4world_env.evaluate, "evaluate"),
    (m4world_env.agreement.run, "run_agreement"),
    (m4world_env.text_embeddings, "precompute_text_embeddings"),
    (m4world_env.gallery, "make_gallery"),
    (m4world_env.evalset, "record_evalset"),
    (gymnasium, "make"),  # m4world demo's env
    (subprocess, "run"),  # m4world bench's benchmarks
]


class WorkStarted(AssertionError):  # noqa: N818 (a failed test; no command's error handler catches it)
    """A command went on to its work with a malformed flag."""


@pytest.fixture(scope="module", autouse=True)
def no_work(tmp_path_factory) -> Iterator[None]:
    """Every work function refuses, the parsers are built once, and the commands run in a folder
    holding an empty ``data/`` (each example leaves it as it found it)."""
    folder = tmp_path_factory.mktemp("cli")
    (folder / "data").mkdir()
    with pytest.MonkeyPatch.context() as mp:
        for module, name in WORK:

            def refuse(*_, _name: str = name, **__) -> None:
                raise WorkStarted(f"{_name} was called")

            mp.setattr(module, name, refuse)
        for module in (m4world_cli, train_cli):  # parsing again and again is all these tests do
            mp.setattr(module, "build_parser", functools.cache(module.build_parser))
        mp.chdir(folder)
        yield


def _recipe_main(argv: list[str]) -> int:
    return world_model.train.recipe.main(argv)


Main = Callable[[list[str]], int]
COMMANDS: dict[str, tuple[Main, list[str], str]] = {  # a valid call (OUT: its output) and its output's name
    "recipe": (_recipe_main, ["--out", "OUT", "--scale", "dry", "--device", "cpu", "--no-progress"], "out"),
    "record": (m4world_cli.main, ["record", "--scenario", "empty_highway", "--out", "OUT"], "out"),
    "eval": (m4world_cli.main, ["eval", "--scenarios", "empty_highway", "--out", "OUT"], "out.json"),
    "demo": (m4world_cli.main, ["demo", "--backend", "procedural", "--out", "OUT"], "out.mp4"),
    "train": (train_cli.main, ["--stage", "vae", "--data", "data", "--run", "OUT", "--device", "cpu"], "run"),
    "m4world train": (m4world_cli.main, ["train", "--stage", "vae", "--data", "data", "--run", "OUT"], "run"),
    "agreement": (m4world_cli.main, ["agreement", "--out", "OUT"], "out"),
    "text-embeddings": (m4world_cli.main, ["text-embeddings", "--scenario", "empty_highway", "--out", "OUT"], "e.npz"),
    "gallery": (m4world_cli.main, ["gallery", "--out", "OUT"], "out"),
}
TRAIN_POSITIVE = ["--steps", "--batch-size", "--ckpt-every", "--lora-rank", "--student-depth", "--context-frames"]
FLAGS = {  # (command, flag) by the class of value the flag takes
    "positive_int": [("recipe", "--workers")]
    + [("record", f) for f in ("--episodes", "--height", "--width", "--workers")]
    + [("eval", f) for f in ("--episodes", "--seeds", "--max-steps", "--context-frames")]
    + [("demo", "--scale"), ("text-embeddings", "--episodes"), ("text-embeddings", "--steps")]
    + [("train", f) for f in (*TRAIN_POSITIVE, "--long-frames")]
    + [("m4world train", "--batch-size")]
    + [("agreement", f) for f in ("--seeds", "--steps", "--jobs")]
    + [("gallery", "--height"), ("gallery", "--width")],
    "non_negative_int": [("eval", "--max-clips"), ("eval", "--sink-frames"), ("demo", "--steps")]
    + [("train", "--long-skip-chunks"), ("agreement", "--videos")],
    "seed": [(c, "--seed") for c in ("recipe", "record", "eval", "demo", "train", "agreement", "text-embeddings")],
    "positive_float": [("recipe", "--max-file-mib"), ("recipe", "--time-limit-s"), ("record", "--duration")]
    + [("gallery", "--seconds"), ("train", "--lr"), ("train", "--dmd-guidance-scale")],
    "non_negative_float": [("train", "--lora-box-weight"), ("train", "--vae-object-weight")],
    "probability": [("train", "--denoise-loss-prob")],
}


def _is_a_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


# Not "--": argparse before Python 3.12 drops it from "--flag=--" and passes [] without the type.
NOT_A_NUMBER = st.one_of(
    st.sampled_from(["", " ", "one", "1,5", "0x10", "1e", "-", "=", "None", "[1]"]),
    st.text(max_size=6).filter(lambda t: not _is_a_number(t) and t != "--"),
)
NOT_AN_INTEGER = st.one_of(
    NOT_A_NUMBER, st.sampled_from(["1.5", "2.0", "1e3", "nan", "inf", "-inf"]), st.floats().map(repr)
)
NOT_FINITE = st.sampled_from(["nan", "-nan", "inf", "-inf", "Infinity", "1e999", "-1e999"])
MALFORMED = {
    "positive_int": st.one_of(NOT_AN_INTEGER, st.integers(max_value=0).map(str)),
    "non_negative_int": st.one_of(NOT_AN_INTEGER, st.integers(max_value=-1).map(str)),
    "seed": st.one_of(
        NOT_AN_INTEGER,
        st.integers(max_value=-1).map(str),
        st.integers(min_value=MAX_SEED + 1).map(str),
        st.sampled_from([str(2**64), str(-(2**63)), str(10**30)]),
    ),
    "positive_float": st.one_of(
        NOT_A_NUMBER, NOT_FINITE, st.floats(max_value=0.0, allow_nan=False).map(repr), st.just("-0")
    ),
    "non_negative_float": st.one_of(NOT_A_NUMBER, NOT_FINITE, st.floats(max_value=-1e-300, allow_nan=False).map(repr)),
    "probability": st.one_of(
        NOT_A_NUMBER,
        NOT_FINITE,
        st.floats(min_value=1.0, exclude_min=True, allow_infinity=False).map(repr),
        st.floats(max_value=-1e-300, allow_infinity=False).map(repr),
    ),
}


def _run(command: str, flags: list[str], out: str | None = None) -> tuple[int, str, list[str]]:
    """Run ``command`` with ``flags`` (its output at ``out``, made first as a folder when it ends in
    ``/``, else as a file; by default the command's own name, left absent); returns the exit
    status, stderr and what the folder holds afterwards that it did not hold before (removed)."""
    main, argv, default_out = COMMANDS[command]
    if out is not None and out.endswith("/"):
        Path(out).mkdir()
    elif out is not None:
        Path(out).write_text("mine")
    before = set(Path().rglob("*"))
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                status = main([(out or default_out) if a == "OUT" else a for a in argv] + flags)
            except SystemExit as e:  # argparse's refusal
                status = e.code
    finally:
        written = set(Path().rglob("*")) - before
        for path in sorted(written | ({Path(out)} if out else set()), reverse=True):
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    return status, err.getvalue(), sorted(map(str, written))


def _assert_refused(status: int, err: str, written: list[str], *names: str) -> None:
    assert status == 2, (status, err)
    assert all(name in err for name in names), (names, err)
    assert "Traceback" not in err and not written, (err, written)


@pytest.mark.parametrize(("kind", "command", "flag"), [(k, c, f) for k, pairs in FLAGS.items() for c, f in pairs])
@PER_FLAG
@given(data=st.data())
def test_a_malformed_flag_value_is_refused_by_name_before_any_work(kind, command, flag, data):
    value = data.draw(MALFORMED[kind], label="value")
    status, err, written = _run(command, [f"{flag}={value}"])
    _assert_refused(status, err, written, flag, repr(value))


FOLDER_OUTPUTS = [("recipe", "--out"), ("record", "--out"), ("agreement", "--out"), ("gallery", "--out")]
FOLDER_OUTPUTS += [("train", "--run"), ("m4world train", "--run")]
FILE_OUTPUTS = [("eval", "--out", ""), ("demo", "--out", ".mp4"), ("text-embeddings", "--out", ".npz")]
NAMES = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_-]{0,7}", fullmatch=True)


@pytest.mark.parametrize(("command", "flag"), FOLDER_OUTPUTS)
@PER_FLAG
@given(name=NAMES.filter(lambda n: n != "data"))
def test_a_file_where_a_folder_is_written_is_refused_before_any_work(command, flag, name):
    status, err, written = _run(command, [], out=name)
    _assert_refused(status, err, written, f"{flag} {name} is a file")


@pytest.mark.parametrize(("command", "flag", "suffix"), FILE_OUTPUTS)
@PER_FLAG
@given(name=NAMES.filter(lambda n: n != "data"))
def test_a_folder_where_a_file_is_written_is_refused_before_any_work(command, flag, suffix, name):
    status, err, written = _run(command, [], out=f"{name}{suffix}/")
    _assert_refused(status, err, written, f"{flag} {name}{suffix}/ is a directory")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["evalset", "--out", "a_file"], "--out a_file is a file"),
        (["bench", "--out", "a_file"], "--out a_file is a file"),
        (["export", "--run", "data", "--out", "a_file"], "--out a_file is a file"),
        (["export", "--run", "missing", "--out", "new"], "--run missing: no such folder"),
        (["export", "--run", "a_file", "--out", "new"], "--run a_file: a file, not a folder"),
    ],
)
def test_other_output_and_input_folders_are_checked_before_any_work(argv, message):
    Path("a_file").write_text("mine")
    before = set(Path().rglob("*"))
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            status = m4world_cli.main(argv)
        written = sorted(map(str, set(Path().rglob("*")) - before))
    finally:
        Path("a_file").unlink()
    _assert_refused(status, err.getvalue(), written, message)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--from-bundle", "data"], "--from-bundle: data is not a checkpoint bundle"),
        (["--max-file-mib", "1e-9"], "--max-file-mib must be a finite size of at least one byte"),
        (["--phases", "paint"], "--phases takes one or more of"),
        (["--join", "missing", "dest"], "--join PARTS missing: no such folder"),
    ],
)
def test_recipe_inputs_are_checked_before_any_work(flags, message):
    status, err, written = _run("recipe", flags)
    _assert_refused(status, err, written, message)
