"""Property-based fuzzing of ``m4world import nuscenes`` on the miniature dataset
(:mod:`tests.nuscenes_mini`) with its table rows and map expansion mutated: fields dropped or
retyped, rows nulled, numbers made non-finite, quaternions zeroed, timestamps reversed, sizes
negated, tokens left dangling. Every import either stops with one error line that names the table
file and the field, having written nothing, or writes clips whose every number is finite; never a
traceback and never a half clip.

Derandomized like :mod:`tests.test_fuzz` (its settings; ``FUZZ_EXAMPLES`` scales the cases).
"""

import contextlib
import copy
import io
import json
import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("nuscenes")

from m4world_env.cli import main  # noqa: E402
from tests import nuscenes_mini as mini  # noqa: E402
from tests.test_fuzz import EXAMPLES, FUZZ, NASTY, _paths  # noqa: E402
from world_model.data import list_clips, read_clip  # noqa: E402

CASES = settings(FUZZ, max_examples=max(EXAMPLES // 5, 10))
# The fields the importer reads, per table: dropping or retyping any of them is refused by name.
READ_FIELDS = {
    "scene": ("token", "name", "first_sample_token", "log_token"),
    "sample": ("token", "timestamp", "next"),
    "sample_data": (
        "token",
        "sample_token",
        "ego_pose_token",
        "calibrated_sensor_token",
        "timestamp",
        "is_key_frame",
        "filename",
        "width",
        "height",
        "prev",
        "next",
    ),
    "ego_pose": ("token", "translation", "rotation"),
    "calibrated_sensor": ("token", "sensor_token", "translation", "rotation", "camera_intrinsic"),
    "sensor": ("token", "channel"),
    "sample_annotation": ("token", "sample_token", "instance_token", "translation", "size", "rotation"),
    "instance": ("token", "category_token"),
    "category": ("token", "name"),
    "log": ("token", "location"),
}
# Fields holding a token of a row (of the table in the value).
REFERENCES = {
    ("scene", "first_sample_token"): "sample",
    ("scene", "log_token"): "log",
    ("sample", "next"): "sample",
    ("sample_data", "sample_token"): "sample",
    ("sample_data", "ego_pose_token"): "ego_pose",
    ("sample_data", "calibrated_sensor_token"): "calibrated_sensor",
    ("sample_data", "prev"): "sample_data",
    ("calibrated_sensor", "sensor_token"): "sensor",
    ("sample_annotation", "instance_token"): "instance",
    ("instance", "category_token"): "category",
}
TEXT_FIELDS = {"name", "channel", "location", "filename", "token", *(f for _, f in REFERENCES)}
VECTORS = {  # fields of finite numbers: (table, field) -> length
    ("ego_pose", "translation"): 3,
    ("ego_pose", "rotation"): 4,
    ("calibrated_sensor", "translation"): 3,
    ("calibrated_sensor", "rotation"): 4,
    ("sample_annotation", "translation"): 3,
    ("sample_annotation", "rotation"): 4,
    ("sample_annotation", "size"): 3,
}
ROTATIONS = [key for key in VECTORS if key[1] == "rotation"]
NON_FINITE = st.sampled_from([math.nan, math.inf, -math.inf])


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    root = mini.write_mini_nuscenes(tmp_path_factory.mktemp("nuscenes_base"))
    return root, mini.load_tables(root), json.loads(mini.map_file(root).read_text())


def _import(root, out, *args):
    """``m4world import nuscenes`` at the tiny preset: the exit code and what it printed to stderr."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main(["import", "nuscenes", "--dataroot", str(root), "--out", str(out), "--preset", "tiny", *args])
    return rc, err.getvalue()


def _finite_json(value, where):
    if isinstance(value, float):
        assert math.isfinite(value), where
    elif isinstance(value, dict):
        for v in value.values():
            _finite_json(v, where)
    elif isinstance(value, list):
        for v in value:
            _finite_json(v, where)


def _assert_refused_or_finite(out, rc, err):
    """Either one error line and nothing written, or whole clips with finite numbers only."""
    if rc != 0:
        assert rc == 2 and err.count("\n") == 1 and err.startswith("m4world import: error: "), err
        assert not out.exists(), err  # refused before the first clip: nothing written
        return err
    clips = list_clips(out)
    assert clips and sorted(p.name for p in out.iterdir() if p.is_dir()) == sorted(clips)  # no half clip
    for name in clips:
        clip = read_clip(out, name)
        assert np.all(np.isfinite(clip.lidar)), name
        _finite_json(json.loads((out / name / "meta.json").read_text()), f"{name}/meta.json")
        for line in (out / name / "frames.jsonl").read_text().splitlines():
            _finite_json(json.loads(line), f"{name}/frames.jsonl")
    return None


def _mutate(data, tree, values):
    """A copy of ``tree`` with one position in it (drawn) replaced by one of ``values`` or deleted."""
    tree = copy.deepcopy(tree)
    path = data.draw(st.sampled_from([p for p, _ in _paths(tree)]), label="where")
    parent = tree
    for key in path[:-1]:
        parent = parent[key]
    if data.draw(st.booleans(), label="replace"):
        parent[path[-1]] = data.draw(values, label="value")
    else:
        del parent[path[-1]]
    return tree


VALUES = st.one_of(NASTY, NON_FINITE, st.just([0, 0, 0, 0]), st.just([-1.0, 1.0, 1.0]))


@CASES
@given(data=st.data())
def test_mutated_tables_are_refused_by_table_and_field_or_import_finite(base, tmp_path_factory, data):
    root, tables, _ = base
    name = data.draw(st.sampled_from(sorted(t for t, rows in tables.items() if rows)), label="table")
    changed = dict(tables)
    whole = data.draw(st.integers(0, 9), label="whole table if 0") == 0
    changed[name] = data.draw(NASTY, label="table") if whole else _mutate(data, tables[name], VALUES)
    work = tmp_path_factory.mktemp("fuzz_tables")
    dataroot = mini.copy_with_tables(root, work / "ns", changed)
    rc, err = _import(dataroot, work / "out")
    if refusal := _assert_refused_or_finite(work / "out", rc, err):
        table = re.search(rf"{re.escape(str(dataroot / mini.VERSION))}/(\w+)\.json", refusal)
        assert table and table[1] in READ_FIELDS, refusal  # the table file, one the importer reads
        assert re.search(r"field '\w+'|a table is a JSON list|row #\d+ is|not valid JSON|keyframe", refusal)


def _break_a_rule(draw, tables):
    """One rule broken on purpose in one row: (tables, table, field, row token, text the error shows)."""
    tables = copy.deepcopy(tables)
    kind = draw(
        st.sampled_from(["drop", "retype", "non_finite", "zero_quaternion", "reversed", "negative_size", "dangling"])
    )
    if kind in ("drop", "retype"):
        table = draw(st.sampled_from(sorted(READ_FIELDS)))
        field = draw(st.sampled_from(READ_FIELDS[table]))
    elif kind == "non_finite":
        table, field = draw(st.sampled_from(sorted(VECTORS)))
    elif kind == "zero_quaternion":
        table, field = draw(st.sampled_from(ROTATIONS))
    elif kind == "negative_size":
        table, field = "sample_annotation", "size"
    elif kind == "reversed":
        table, field = draw(st.sampled_from(["sample", "sample_data"])), "timestamp"
    else:
        table, field = draw(st.sampled_from(sorted(REFERENCES)))
    rows = tables[table]
    if kind == "reversed":  # a row timed at or before the row before it in its chain
        rows = [r for r in rows if r["prev"]]
    row = rows[draw(st.integers(0, len(rows) - 1))]
    if kind == "drop":
        del row[field]
        shown = "is missing"
    elif kind == "retype":
        wrong = [None, 7, 1.5, [], {}] if field in TEXT_FIELDS else [None, "1", {}]
        row[field] = draw(st.sampled_from(wrong if field != "is_key_frame" else [None, 1, "true"]))
        shown = f"is {row[field]!r}"
    elif kind == "non_finite":
        bad = draw(NON_FINITE)
        row[field][draw(st.integers(0, VECTORS[(table, field)] - 1))] = bad
        shown = repr(bad)
    elif kind == "zero_quaternion":
        row[field] = [0, 0, 0, 0]
        shown = "is [0, 0, 0, 0]"
    elif kind == "negative_size":
        bad = draw(st.sampled_from([0.0, -1.0, -1e-9]))
        row[field][draw(st.integers(0, 2))] = bad
        shown = repr(bad)
    elif kind == "reversed":
        before = next(r for r in tables[table] if r["token"] == row["prev"])
        row[field] = before[field] - draw(st.integers(0, 10**6))
        shown = "strictly increase"
    else:
        row[field] = "nope"
        shown = "is 'nope'"
    token = row["token"] if field != "token" else None
    return tables, table, field, token, shown


@CASES
@given(data=st.data())
def test_each_broken_rule_is_refused_naming_table_row_and_field(base, tmp_path_factory, data):
    root, tables, _ = base
    changed, table, field, token, shown = _break_a_rule(data.draw, tables)
    work = tmp_path_factory.mktemp("fuzz_rows")
    dataroot = mini.copy_with_tables(root, work / "ns", changed)
    rc, err = _import(dataroot, work / "out")
    refusal = _assert_refused_or_finite(work / "out", rc, err)
    assert refusal, f"{table}.{field} broken, yet imported"
    assert f"{dataroot / mini.VERSION / table}.json: " in refusal and f"field {field!r}" in refusal, refusal
    assert token is None or repr(token) in refusal, refusal
    assert shown in refusal, refusal


@CASES
@given(data=st.data())
def test_mutated_map_expansions_are_refused_by_layer_or_import_finite(base, tmp_path_factory, data):
    root, tables, layers = base
    layers = _mutate(data, layers, st.one_of(NASTY, NON_FINITE))
    work = tmp_path_factory.mktemp("fuzz_map")
    dataroot = mini.copy_with_tables(root, work / "ns", tables, layers=layers)
    rc, err = _import(dataroot, work / "out", "--scenes", "scene-0002")
    if refusal := _assert_refused_or_finite(work / "out", rc, err):
        assert f"{mini.map_file(dataroot)}: " in refusal and "layer '" in refusal, refusal
