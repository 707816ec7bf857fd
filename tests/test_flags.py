"""One definition of the estimate flags (``kernels.flags.EstimateFlag``) for the numerics, the schema and
docs/estimates.md; the schema loads without Numba."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from feedio import schema as S
from kernels import flags, online
from kernels.flags import DESCRIPTIONS, EstimateFlag, markdown_table

ESTIMATES_DOC = Path(__file__).resolve().parents[1] / "docs" / "estimates.md"


def test_the_bits_are_the_contract_and_the_schema_uses_them():
    assert {f.name: int(f) for f in EstimateFlag} == {"STALE": 1, "GAP": 2, "REJECTED": 4, "WARMUP": 8, "REDUCED": 16}
    assert S.EstimateFlag is EstimateFlag
    assert (S.STALE, S.GAP, S.REJECTED, S.WARMUP, S.REDUCED) == tuple(EstimateFlag)
    assert all(S.FLAG_NAMES[int(f)] == f.name for f in EstimateFlag)
    assert S.flag_names(int(EstimateFlag.GAP | EstimateFlag.WARMUP) | 64) == ["GAP", "WARMUP"]
    assert S.flag_names(np.int64(4)) == ["REJECTED"]
    # the plain ints the @njit loop uses come from the IntFlag
    assert [flags.STALE_BIT, flags.GAP_BIT, flags.REJECTED_BIT, flags.WARMUP_BIT, flags.REDUCED_BIT] == \
        [int(f) for f in EstimateFlag]
    assert online.STALE_BIT is flags.STALE_BIT and set(DESCRIPTIONS) == set(EstimateFlag)


def test_docs_flags_table_is_the_intflag():
    text = ESTIMATES_DOC.read_text(encoding="utf-8")
    m = re.search(r"<!-- flags-table:start -->\n(.*?)\n<!-- flags-table:end -->", text, re.S)
    assert m, "docs/estimates.md has no flags table between the markers"
    assert m.group(1) == markdown_table(), "docs/estimates.md flags table differs from kernels.flags; paste markdown_table()"


def test_schema_and_status_do_not_load_numba():
    code = ("import sys\nimport feedio.schema, kernels.flags\nfrom kernels import EstimateFlag\n"
            "import feedmon.status_cmd\nassert 'numba' not in sys.modules, 'numba loaded'\n"
            "from kernels import KRLST\nassert 'numba' in sys.modules\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
