"""One compiled specialisation per function: no ``@njit`` function passes a bare ``True``/``False`` or
integer literal to another compiled function. Numba types such an argument ``Literal[bool](True)`` /
``Literal[int](0)`` and compiles the callee once more for it, beside the ``bool``/``int64`` version the
other callers use — each extra copy of ``joint_update`` cost ~9 s of a cold compile (CI, the Docker
warm-up). Pass ``np.bool_(True)``/``np.int64(0)`` instead (docs/design-decisions.md, "Literal
arguments"). Callees inlined at the IR level (``inline="always"``) are not compiled apart and are exempt."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
from pathlib import Path

from numba.core.dispatcher import Dispatcher

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("kernels", "feedio", "replay", "monitor")

#: (module, callee) pairs whose literal arguments are the point: ``kernel_row`` and ``kernel_row_at``
#: are the two specialisations of ``_rows`` (``use_idx`` False/True, the branch pruned at compile time)
BY_DESIGN = {("kernels.covariance", "_rows")}


def _is_jitted(fn: ast.FunctionDef) -> bool:
    return any("jit" in ast.unparse(d) for d in fn.decorator_list)


def _callee(mod, func: ast.expr):
    if isinstance(func, ast.Name):
        return func.id, getattr(mod, func.id, None)
    if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name):
        return func.attr, getattr(getattr(mod, func.value.id, None), func.attr, None)
    return None, None


def _literal(arg: ast.expr) -> bool:
    if isinstance(arg, ast.UnaryOp) and isinstance(arg.op, ast.USub | ast.UAdd):
        arg = arg.operand
    return isinstance(arg, ast.Constant) and isinstance(arg.value, bool | int)


def literal_calls(mod, source: str) -> list[str]:
    """``function:line callee(arg)`` for each bare bool/int literal a compiled function of ``mod``
    passes to a compiled (not IR-inlined) function."""
    out = []
    for fn in ast.walk(ast.parse(source)):
        if not (isinstance(fn, ast.FunctionDef) and _is_jitted(fn)):
            continue
        for call in ast.walk(fn):
            if not isinstance(call, ast.Call):
                continue
            name, obj = _callee(mod, call.func)
            if not isinstance(obj, Dispatcher) or obj.targetoptions.get("inline", "never") == "always":
                continue
            if (obj.py_func.__module__, name) in BY_DESIGN:
                continue
            out += [f"{mod.__name__}.{fn.name}:{call.lineno} {name}({ast.unparse(a)})"
                    for a in [*call.args, *(k.value for k in call.keywords)] if _literal(a)]
    return out


def test_no_compiled_call_passes_a_literal():
    found = []
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            source = path.read_text(encoding="utf-8")
            if "jit" not in source:
                continue
            name = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
            found += literal_calls(importlib.import_module(name), source)
    assert not found, "literal arguments to compiled functions (a second specialisation each): " + "; ".join(found)


def test_the_check_finds_a_literal_argument(tmp_path):
    """The check itself: a literal bool and a literal int passed from one compiled function to another are
    reported; a variable, an ``np.int64(0)`` and a call of an IR-inlined function are not."""
    src = ("import numpy as np\nfrom numba import njit\n\n"
           "@njit\ndef f(a, b):\n    return a + b\n\n"
           "@njit(inline='always')\ndef g(a, b):\n    return a - b\n\n"
           "@njit\ndef h(x):\n    k = x\n"
           "    return f(x, True) + f(x, -1) + f(k, np.int64(0)) + g(x, 0)\n")
    path = tmp_path / "litmod.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("litmod", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["litmod"] = mod
    try:
        spec.loader.exec_module(mod)
        assert literal_calls(mod, src) == ["litmod.h:15 f(True)", "litmod.h:15 f(-1)"]
    finally:
        del sys.modules["litmod"]
