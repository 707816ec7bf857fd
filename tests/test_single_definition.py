"""One definition per constant: a public module-level constant (an ``UPPER_CASE`` name) is assigned in
one module of the package only; every other module imports it. Two modules assigning the same name
either repeat a value (which then drifts: the spindle-speed limit once had three) or give one name two
meanings (``PHYSICAL`` once meant both the β parameter names and the per-sample limits)."""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("feedio", "monitor", "feedmon", "replay", "bridge", "kernels")
CONSTANT = re.compile(r"[A-Z][A-Z0-9_]*")

#: names every module of a kind defines for itself by design, one meaning per module: a compiled state's
#: field list, its layout and the fields its snapshot saves (:mod:`kernels.layout`), a message's fields
PER_MODULE = {"FIELDS", "LAYOUT", "STATE_FIELDS"}


def module_constants(source: str) -> list[tuple[str, int]]:
    """``(name, line)`` of every public constant assigned at module level (plain, annotated or
    tuple-unpacking assignment; an import is not an assignment)."""
    out = []
    for node in ast.parse(source).body:
        if isinstance(node, ast.Assign):
            targets = [e for t in node.targets for e in (t.elts if isinstance(t, ast.Tuple | ast.List) else [t])]
        elif isinstance(node, ast.AnnAssign) and node.value is not None:
            targets = [node.target]
        else:
            continue
        out += [(t.id, node.lineno) for t in targets if isinstance(t, ast.Name) and CONSTANT.fullmatch(t.id)]
    return out


def duplicates(root: Path) -> dict[str, list[str]]:
    """Constant name → ``path:line`` of each assignment, for names assigned in more than one module."""
    where: dict[str, list[str]] = defaultdict(list)
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            for name, line in module_constants(path.read_text(encoding="utf-8")):
                where[name].append(f"{path.relative_to(root).as_posix()}:{line}")
    return {name: places for name, places in where.items() if len({p.split(":")[0] for p in places}) > 1}


def test_no_constant_is_assigned_in_two_modules():
    found = {name: places for name, places in duplicates(REPO).items() if name not in PER_MODULE}
    assert not found, ("constants assigned in more than one module (define each once and import it): "
                       + "; ".join(f"{name} at {', '.join(places)}" for name, places in sorted(found.items())))


def test_the_check_finds_a_repeated_constant(tmp_path):
    """The check itself: a name assigned in two modules (plainly and by unpacking) is reported, an import
    and a private name are not."""
    pkg = tmp_path / "feedio"
    pkg.mkdir()
    (pkg / "a.py").write_text("MAGIC = b'x'\n_LOCAL = 1\nfrom b import OTHER\n")
    (pkg / "b.py").write_text("OTHER = 2\nMAGIC, SECOND = b'x', 3\n_LOCAL = 2\n")
    for name in PACKAGES[1:]:
        (tmp_path / name).mkdir()
    assert duplicates(tmp_path) == {"MAGIC": ["feedio/a.py:1", "feedio/b.py:2"]}
