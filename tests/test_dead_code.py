"""No dead code: vulture over the whole tree (the code, its tests, benchmarks and tools), with the
dynamic uses it cannot see in ``tools/vulture_whitelist.py``; and no public name (``__all__``) that
nothing else uses. Unused functions, methods, properties, classes and imports are reported at every
confidence (vulture rates them 60–90 %); variables and attributes only at ≥ 80 %, because msgspec
Struct and dataclass fields are read by name from outside the code and vulture calls them unused
attributes at 60 %."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import vulture

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("kernels", "feedio", "monitor", "replay", "bridge", "feedmon", "benchmarks", "tools", "tests", "deploy")
WHITELIST = ROOT / "tools" / "vulture_whitelist.py"
#: what vulture finds reliably at its lowest confidence
ALWAYS = {"function", "method", "property", "class", "import"}
#: dead code in files that another change rewrites at the same time: listed here, deleted there
#: (remove an entry together with its code)
KNOWN_DEAD = {
    ("kernels/_krlst_core.py", "predict"),
    ("kernels/beta_tracker.py", "_lu_solve_t"),
    ("kernels/least_squares.py", "predict"),
    ("kernels/likelihood.py", "toeplitz_column"),
    ("kernels/feed_drive.py", "predict_one_step"),
    ("kernels/health.py", "new_health_state"),
    ("monitor/online_settings.py", "parse_model_tables"),
    ("monitor/online_settings.py", "PER"),
    ("monitor/identify/candidates.py", "trial_exo_name"),
}


def _files() -> list[Path]:
    return sorted(p for d in SCANNED for p in (ROOT / d).rglob("*.py"))


def _rel(path) -> str:
    return Path(path).resolve().relative_to(ROOT).as_posix()


def test_vulture_finds_no_dead_code():
    v = vulture.Vulture()
    v.scavenge([str(ROOT / d) for d in SCANNED] + [str(WHITELIST)])
    found = [f"{_rel(i.filename)}:{i.first_lineno}: unused {i.typ} {i.name!r} ({i.confidence} %)"
             for i in v.get_unused_code()
             if (i.typ in ALWAYS or i.confidence >= 80) and (_rel(i.filename), i.name) not in KNOWN_DEAD]
    assert not found, ("dead code (delete it; a name used where vulture cannot see goes into "
                       "tools/vulture_whitelist.py with who uses it):\n" + "\n".join(found))


def test_every_public_name_is_used_outside_its_module():
    texts = {p: p.read_text(encoding="utf-8") for p in _files()}
    unused = []
    for path, text in texts.items():
        for node in ast.parse(text).body:
            if not (isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets)):
                continue
            try:
                names = ast.literal_eval(node.value)
            except ValueError:
                continue  # an __all__ computed at import (a list of a module's names): nothing to check by hand
            for name in names:
                word = re.compile(rf"\b{re.escape(name)}\b")
                if len(word.findall(text)) > 2 or (_rel(path), name) in KNOWN_DEAD:
                    continue  # used in its own module beyond the definition and __all__
                if not any(word.search(t) for q, t in texts.items() if q != path):
                    unused.append(f"{_rel(path)}: {name}")
    assert not unused, "names exported in __all__ that nothing uses (delete them):\n" + "\n".join(unused)


def test_the_check_sees_dead_code(tmp_path):
    """The check itself can fail: a module with a dead function and a dead import is reported."""
    (tmp_path / "m.py").write_text("import os\n\n\ndef used():\n    return 1\n\n\ndef dead():\n    return 2\n\n\n"
                                   "print(used())\n", encoding="utf-8")
    v = vulture.Vulture()
    v.scavenge([str(tmp_path)])
    assert {(i.typ, i.name) for i in v.get_unused_code()} == {("import", "os"), ("function", "dead")}
