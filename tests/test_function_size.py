"""No function of the library packages runs over MAX_LINES lines or takes more than MAX_PARAMETERS
parameters, save one that says why on the line right above its ``def`` (or its first decorator):
``# function-size: <why>``."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("world_model", "m4world_env")
MAX_LINES = 80  # from the ``def`` line to the last line of the body, docstring included
MAX_PARAMETERS = 8  # a method's ``self`` or ``cls`` not counted
REASON = "# function-size:"


def _parameters(fn: ast.FunctionDef | ast.AsyncFunctionDef, in_class: bool) -> int:
    a = fn.args
    names = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
    names += [p.arg for p in (a.vararg, a.kwarg) if p is not None]
    if in_class and names[:1] in (["self"], ["cls"]):
        names = names[1:]
    return len(names)


def _has_reason(fn: ast.FunctionDef | ast.AsyncFunctionDef, lines: list[str]) -> bool:
    first = min([fn.lineno, *(d.lineno for d in fn.decorator_list)])
    above = lines[first - 2].strip() if first >= 2 else ""
    return above.startswith(REASON) and len(above) > len(REASON) + 1


def offenders_in(source: str, path: str) -> dict[str, str]:
    """``path::Qualified.name`` -> what is over the limits, for each function of ``source`` over
    one without a reason line."""
    lines = source.splitlines()
    found: dict[str, str] = {}

    def visit(node: ast.AST, prefix: str, in_class: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.", True)
            elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}{child.name}"
                length, params = child.end_lineno - child.lineno + 1, _parameters(child, in_class)
                over = [f"{length} lines"] * (length > MAX_LINES) + [f"{params} parameters"] * (params > MAX_PARAMETERS)
                if over and not _has_reason(child, lines):
                    found[f"{path}::{name}"] = ", ".join(over)
                visit(child, f"{name}.", False)

    visit(ast.parse(source), "", False)
    return found


def library_offenders() -> dict[str, str]:
    found: dict[str, str] = {}
    for package in PACKAGES:
        for file in sorted((ROOT / package).rglob("*.py")):
            found |= offenders_in(file.read_text(), file.relative_to(ROOT).as_posix())
    return found


def test_the_checker_counts_lines_and_parameters_and_reads_a_reason():
    nine = "def f(a, b, c, d, e, f, g, h, i):\n    pass\n"
    assert offenders_in(nine, "m.py") == {"m.py::f": "9 parameters"}
    assert offenders_in(f"{REASON} a reason\n{nine}", "m.py") == {}
    assert offenders_in(f"{REASON}\n{nine}", "m.py") == {"m.py::f": "9 parameters"}  # a reason says something
    method = "class C:\n    @staticmethod\n    def g(self, a, b, c, d, e, f, g, h):\n        pass\n"
    assert offenders_in(method, "m.py") == {}  # self is not counted; the decorator is no body line
    long = "def outer():\n    def inner(*args, **kwargs):\n" + "        x = 1\n" * MAX_LINES
    assert offenders_in(long, "m.py") == {"m.py::outer": f"{MAX_LINES + 2} lines", "m.py::outer.inner": "81 lines"}


def test_no_library_function_is_over_80_lines_or_8_parameters_without_a_reason():
    found = library_offenders()
    assert not found, f"split these, or say why above the def ({REASON} ...): {found}"
