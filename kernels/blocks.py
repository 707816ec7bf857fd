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

Samples left out of the fit (``keep`` False: the friction law does not describe them) are a block of
their own that carries nothing (infinite variance: weight 0), and the disturbance's correlation across
them is left out as across a closed gate.
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
    lags asked for), or None for a closed gate (``A = γ⁻¹I`` there); ``kept`` False: left out of the fit."""

    start: int
    stop: int
    column: np.ndarray | None
    kept: bool = True

    @property
    def size(self) -> int:
        return self.stop - self.start


def gate_runs_of(code: np.ndarray) -> list[tuple[int, int, int]]:
    """``(start, stop, value)`` of the runs of equal value of the integer array ``code``."""
    c = np.asarray(code)
    edges = np.flatnonzero(np.diff(c)) + 1
    bounds = np.concatenate([[0], edges, [c.size]]).astype(int)
    return [(int(a), int(b), int(c[a])) for a, b in zip(bounds[:-1], bounds[1:])]


def gate_runs(gate: np.ndarray) -> list[tuple[int, int, bool]]:
    """``(start, stop, open)`` of the runs of equal value of the boolean ``gate``."""
    return [(a, b, bool(v)) for a, b, v in gate_runs_of(np.asarray(gate, dtype=np.int8))]


def blocks(kernel: Kernel, gamma: float, Ts: float, n: int, *, gate=None, phase: PhaseSegments | None = None,
           max_order: int | None = None, keep=None) -> list[Block]:
    """The blocks of (B1) for ``n`` samples of period ``Ts``: one per run of an open ``gate`` (None: open
    everywhere) within each stretch of ``phase`` (None: one time kernel over the record), columns of at most
    ``max_order + 1`` lags; one closed block per run of a closed gate; one left-out block per run of
    ``keep`` False."""
    flags = []
    for name, mask in (("gate", gate), ("keep", keep)):
        if mask is not None:
            mask = np.asarray(mask, dtype=bool)
            if mask.shape != (n,):
                raise ValueError(f"the {name} mask has {mask.size} samples, the regression {n}")
        flags.append(mask)
    gate, keep = flags
    code = np.ones(n, dtype=np.int8) if gate is None else gate.astype(np.int8)  # 1 open, 0 closed, 2 left out
    if keep is not None:
        code[~keep] = 2
    runs = [(a, b, int(code[a])) for a, b, _ in gate_runs_of(code)]
    stretches = [(0, n, None)] if phase is None else [
        (int(a), int(b), float(w)) for a, b, w in zip(phase.edges[:-1], phase.edges[1:], phase.rate)]
    shift = 1.0 / float(gamma)
    out: list[Block] = []
    for a0, b0, rate in stretches:
        for a1, b1, open_ in runs:
            a, b = max(a0, a1), min(b0, b1)
            if a >= b:
                continue
            if open_ != 1:
                out.append(Block(a, b, None, kept=open_ == 0))
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
