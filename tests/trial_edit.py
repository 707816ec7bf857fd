"""Copies of a one-axis trial file with its sample blocks changed (truth kept), for tests."""

from __future__ import annotations

from collections.abc import Callable

from feedio.mcapio import OpenTrial, TrialWriter, iter_blocks
from feedio.schema import SampleBlock


def rewrite_samples(src, dst, edit: Callable[[SampleBlock], SampleBlock]):
    """``src`` → ``dst`` with every sample block replaced by ``edit(block)``; returns ``dst``."""
    with OpenTrial(src) as f:
        ((m, a),) = f.axes()
        meta, start = f.meta(m, a), f.start_ns(m, a)
    with TrialWriter(dst, [meta], start=start) as w:
        for kind, b in iter_blocks(src, kinds=("samples", "truth")):
            if kind == "samples":
                w.write_samples(edit(b))
            else:
                w.write_truth(b, m, a)
    return dst
