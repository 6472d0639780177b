"""What the repository ships reads the same on every machine: no machine paths, no dead links."""

import json
import re
from importlib.metadata import requires, version
from pathlib import Path

import pytest
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = [ROOT / "world_model" / "assets", ROOT / "world_model" / "checkpoints", ROOT / "m4world_env" / "scenarios"]
# An absolute POSIX or Windows path, or a home-relative one, inside a string value.
MACHINE_PATH = re.compile(r"^(/[A-Za-z0-9_.-]+/|[A-Za-z]:\\|~/)")


def _strings(value):
    if isinstance(value, str):
        yield value
    elif isinstance(value, dict):
        for k, v in value.items():
            yield str(k)
            yield from _strings(v)
    elif isinstance(value, list):
        for v in value:
            yield from _strings(v)


def _shipped_text_files():
    for root in SHIPPED:
        for path in sorted(root.rglob("*")):
            if path.suffix in {".json", ".yaml", ".yml"}:
                yield path


def test_the_machine_path_pattern_catches_absolute_paths():
    assert MACHINE_PATH.match("/work/m4world_data/train")
    assert MACHINE_PATH.match("C:\\data")
    assert not MACHINE_PATH.match("train")
    assert not MACHINE_PATH.match("blocks\\.\\d+")


@pytest.mark.parametrize("path", list(_shipped_text_files()), ids=lambda p: str(p.relative_to(ROOT)))
def test_shipped_metadata_names_no_machine_path(path):
    if path.suffix == ".json":
        found = [s for s in _strings(json.loads(path.read_text())) if MACHINE_PATH.match(s)]
    else:
        found = re.findall(r"(?m)^\s*[^#\n]*?:\s*['\"]?(/[A-Za-z0-9_.-]+/\S*)", path.read_text())
    assert not found, f"{path.relative_to(ROOT)} names machine paths: {found}"


LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _doc_pages():
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


@pytest.mark.parametrize("page", _doc_pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_in_the_docs_resolves_inside_the_repository(page):
    broken = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"^[a-z]+:", target) or target.startswith("#"):
            continue  # web links and in-page anchors
        file = (page.parent / target.split("#", 1)[0]).resolve()
        if not file.exists() or ROOT not in file.parents:
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)} links to what a user of the repository does not have: {broken}"


GENERATED = {"out", "runs", "data"}  # folders that commands write (git-ignored); their files are outputs
MENTIONED_PAGE = re.compile(r"(?<![\w/.-])((?:\.\./)*[\w./-]*[A-Za-z0-9_-]+\.md)\b")


@pytest.mark.parametrize("page", _doc_pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_page_the_docs_mention_is_in_the_repository(page):
    """Pages named in prose or code spans (``docs/x.md``, ``../y.md``) exist for someone with only the repo."""
    text = LINK.sub("", page.read_text())
    missing = []
    for name in set(MENTIONED_PAGE.findall(text)):
        if name.split("/", 1)[0] in GENERATED:
            continue
        candidates = [(page.parent / name).resolve(), (ROOT / name).resolve()]
        if "/" not in name:
            candidates += list(ROOT.glob(f"**/{name}"))
        if not any(c.exists() and (c == ROOT or ROOT in c.parents) and ".venv" not in c.parts for c in candidates):
            missing.append(name)
    assert not missing, f"{page.relative_to(ROOT)} mentions pages a user of the repository does not have: {missing}"


def _requirement(name: str) -> Requirement:
    """The installed package's requirement on ``name`` (its metadata is pyproject.toml's, as installed)."""
    reqs = [Requirement(r) for r in requires("m4world-gym") or []]
    return next(r for r in reqs if r.name == name and r.marker is None)


def test_the_library_admits_the_torch_2_releases_it_runs_on_so_a_cuda_build_is_kept():
    torch = _requirement("torch")
    for release in ("2.11.0", "2.13.0", "2.14.1"):
        assert torch.specifier.contains(release), f"torch {release} is refused by {torch}"
    assert not torch.specifier.contains("3.0.0")


def test_highway_env_is_bounded_to_the_versions_the_equivalence_tests_cover():
    highway = _requirement("highway-env")
    assert highway.specifier.contains(version("highway-env"))
    assert not highway.specifier.contains("2.0.0"), "traffic/fastmath.py and traffic/sim.py override its internals"


@pytest.mark.parametrize("page", ["README.md", "docs/MODEL_CARD.md"])
def test_the_readme_and_the_model_card_read_in_minutes(page):
    lines = (ROOT / page).read_text().count("\n")
    assert lines <= 250, f"{page} has {lines} lines; keep it a page a user reads in five minutes (<= 250)"
