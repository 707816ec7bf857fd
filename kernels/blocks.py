"""Block-diagonal ``A = Ω + γ⁻¹I`` of a time kernel on a uniform grid: stretches of constant spindle speed
(the spindle-phase kernel, eq. S2 of :mod:`kernels.spindle_phase`) and a gate — the samples where the
disturbance acts at all.

A gate ``g(k) ∈ {0, 1}`` (a process that acts only part of the time: a cut, a shaker switched on) makes
the disturbance ``g(k)·f(k)``, so

    A_ij = g_i g_j k(x_i, x_j) + γ⁻¹ δ_ij                                                      (B1)

— white noise of variance γ⁻¹ (in the units of the profiled scale) where ``g = 0``. Between two
stretches where the gate is open, the correlation of ``f`` across the closed stretch is left out
(each open stretch a realisation of its own, as across a change of spindle speed in S2): a stretch
that carries only the process-free motion then says nothing about the disturbance, and the
regression's friction and offset come from it. Every block is Toeplitz: one Levinson pass each
(exact or of order m, :mod:`kernels.levinson`); a closed block is diagonal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .covariance import Kernel
from .spindle_phase import PhaseSegments

__all__ = ["Block", "blocks", "gate_runs"]


@dataclass(frozen=True)
class Block:
    """Samples ``start:stop``; ``column``: the first column of their Toeplitz block of ``A`` (at most the
    lags asked for), or None for a closed gate (``A = γ⁻¹I`` there)."""

    start: int
    stop: int
    column: np.ndarray | None

    @property
    def size(self) -> int:
        return self.stop - self.start


def gate_runs(gate: np.ndarray) -> list[tuple[int, int, bool]]:
    """``(start, stop, open)`` of the runs of equal value of the boolean ``gate``."""
    g = np.asarray(gate, dtype=bool)
    edges = np.flatnonzero(np.diff(g.astype(np.int8))) + 1
    bounds = np.concatenate([[0], edges, [g.size]]).astype(int)
    return [(int(a), int(b), bool(g[a])) for a, b in zip(bounds[:-1], bounds[1:])]


def blocks(kernel: Kernel, gamma: float, Ts: float, n: int, *, gate=None, phase: PhaseSegments | None = None,
           max_order: int | None = None) -> list[Block]:
    """The blocks of (B1) for ``n`` samples of period ``Ts``: one per run of an open ``gate`` (None: open
    everywhere) within each stretch of ``phase`` (None: one time kernel over the record), columns of at most
    ``max_order + 1`` lags; one closed block per run of a closed gate."""
    if gate is not None:
        gate = np.asarray(gate, dtype=bool)
        if gate.shape != (n,):
            raise ValueError(f"the gate has {gate.size} samples, the regression {n}")
    runs = gate_runs(gate) if gate is not None else [(0, n, True)]
    stretches = [(0, n, None)] if phase is None else [
        (int(a), int(b), float(w)) for a, b, w in zip(phase.edges[:-1], phase.edges[1:], phase.rate)]
    shift = 1.0 / float(gamma)
    out: list[Block] = []
    for a0, b0, rate in stretches:
        for a1, b1, open_ in runs:
            a, b = max(a0, a1), min(b0, b1)
            if a >= b:
                continue
            if not open_:
                out.append(Block(a, b, None))
                continue
            lags = b - a if max_order is None else min(b - a, int(max_order) + 1)
            d = np.arange(lags) * Ts
            if rate is None:
                column = kernel.lag(d)
            else:
                column = kernel(np.zeros((1, 2)), np.column_stack([d, rate * d]))[0]
            column = np.array(column, dtype=np.float64)
            column[0] += shift
            out.append(Block(a, b, column))
    return out
