"""Small modules and functions outside the compiled kernels: a module of at most 800 lines, a function of at
most 120 (a compiled loop, decorated ``njit``, may be longer: splitting it costs speed). A module or function
beyond them holds several concerns; split it by concern."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: the packages checked here (kernels/ has its own layout work)
PACKAGES = ("feedio", "monitor", "feedmon", "replay", "bridge")
MODULE_LINES = 800
FUNCTION_LINES = 120


def _compiled(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    def name(d: ast.expr) -> str:
        d = d.func if isinstance(d, ast.Call) else d
        return d.attr if isinstance(d, ast.Attribute) else getattr(d, "id", "")

    return any(name(d) == "njit" for d in node.decorator_list)


def oversize(root: Path) -> list[str]:
    """``path: what`` of every module and function beyond the limits."""
    found = []
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            text = path.read_text(encoding="utf-8")
            rel = path.relative_to(root).as_posix()
            if text.count("\n") > MODULE_LINES:
                found.append(f"{rel}: {text.count(chr(10))} lines")
            for node in ast.walk(ast.parse(text)):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and not _compiled(node):
                    n = node.end_lineno - node.lineno + 1
                    if n > FUNCTION_LINES:
                        found.append(f"{rel}: {node.name} has {n} lines")
    return found


def test_modules_and_functions_are_small():
    assert oversize(REPO) == []


def test_the_check_finds_a_long_function_and_spares_a_compiled_loop(tmp_path):
    for pkg in PACKAGES:
        (tmp_path / pkg).mkdir()
    body = "".join(f"    x{i} = {i}\n" for i in range(FUNCTION_LINES))
    (tmp_path / "feedio" / "m.py").write_text(f"def long():\n{body}\n\n@njit(cache=True)\ndef loop():\n{body}")
    assert oversize(tmp_path) == [f"feedio/m.py: long has {FUNCTION_LINES + 1} lines"]
