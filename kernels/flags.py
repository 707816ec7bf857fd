"""The bits of ``EstimateBlock.flags`` and the adaptation modes: one definition for the numerics, the
schema, the sinks and the README.

:class:`EstimateFlag` is the definition. Numba cannot type an ``IntFlag`` member inside
``@njit`` code, so the plain ``int`` constants ``*_BIT`` below are derived from it here, once,
for :mod:`kernels.online`. :data:`DESCRIPTIONS` says what each bit means; the README's flags
table is :func:`markdown_table` (a test keeps the two equal).

This module imports nothing but :mod:`enum` (``feedio.schema`` uses it in processes that never
load Numba, e.g. ``feedmon status``).
"""

from __future__ import annotations

import enum

__all__ = ["EstimateFlag", "DESCRIPTIONS", "markdown_table",
           "STALE_BIT", "GAP_BIT", "REJECTED_BIT", "WARMUP_BIT", "REDUCED_BIT", "ADAPTATION_MODES"]

#: the online β's adaptation modes (``[adaptation] mode``, ``Health.adaptation``), in code order: the
#: compiled loop's ``OnlineConfig.mode`` is the index (:data:`kernels.online.MODE_OFF` …)
ADAPTATION_MODES = ("off", "track", "apply")


class EstimateFlag(enum.IntFlag):
    """Bits of the per-row ``flags`` of an estimate (a row may carry several)."""

    STALE = 1
    GAP = 2
    REJECTED = 4
    WARMUP = 8
    REDUCED = 16


#: what each bit means (the README's flags table is made from this)
DESCRIPTIONS: dict[EstimateFlag, str] = {
    EstimateFlag.STALE: "the measured velocity repeats the previous one while the axis moves (a recording "
                        "glitch): the row is predicted from the model, the tracker does not learn from it",
    EstimateFlag.GAP: "the regressor chain restarts here: samples are missing before this one (sequence gap), "
                      "controller time went backwards, or the sequence numbers restarted (a new bridge session); "
                      "no residual is formed across it",
    EstimateFlag.REJECTED: "the sample has a non-finite or absurd value: NaN estimates, the tracker is untouched "
                           "and the next good sample restarts the chain",
    EstimateFlag.WARMUP: "the chain (re)starts at this sample, or the tracker has learned fewer samples than its "
                         "budget M: estimates are not yet reliable",
    EstimateFlag.REDUCED: "KRLS-T reduced update: the newest sample was not added to the dictionary",
}

# plain ints for @njit code, derived from the one definition above
STALE_BIT = int(EstimateFlag.STALE)
GAP_BIT = int(EstimateFlag.GAP)
REJECTED_BIT = int(EstimateFlag.REJECTED)
WARMUP_BIT = int(EstimateFlag.WARMUP)
REDUCED_BIT = int(EstimateFlag.REDUCED)


def markdown_table() -> str:
    """The flags as a Markdown table (bit, name, meaning), as it appears in the README."""
    lines = ["| bit | flag | meaning |", "|---|---|---|"]
    lines += [f"| {int(f)} | `{f.name}` | {DESCRIPTIONS[f]} |" for f in EstimateFlag]
    return "\n".join(lines)
