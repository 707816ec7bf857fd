"""A trial's true disturbance force as a ``halstreamer`` input file: the known truth a HAL plant feeds in.

``feedmon simulate`` writes trials with the true disturbance force (N) per sample; the HAL plant
(``deploy/linuxcnc/plant/``) takes it through ``streamer`` (one value per line, one line per servo
cycle). The trial's sampling period must be the plant's servo period: a force at another rate would
play faster or slower than it was simulated.
"""

from __future__ import annotations

import math
import os

import numpy as np

from feedio.mcapio import read_trial
from kernels.errors import ParameterError

__all__ = ["write_streamer_file"]


def write_streamer_file(trial: str | os.PathLike, output: str | os.PathLike, *, axis: str | None = None,
                        scale: float = 1.0, servo_period: float | None = None) -> int:
    """Write the truth force of ``trial`` (× ``scale``) to ``output``, one value per line; the number of
    lines. ``servo_period`` (s), when given, must be the trial's Ts."""
    if not (math.isfinite(scale) and scale != 0.0 and abs(scale) <= 1e6):
        raise ParameterError(f"scale must be a finite, non-zero factor up to 1e6 in size, got {scale!r}", "scale")
    tr = read_trial(trial, axis)
    if servo_period is not None and not math.isclose(servo_period, tr.Ts, rel_tol=1e-9):
        raise ParameterError(f"{tr.path}: sampled every {tr.Ts:g} s, but the servo period is {servo_period:g} s; "
                             "simulate the trial at the plant's rate (scenario constant 'rate')", "servo_period")
    if tr.truth is None:
        raise ValueError(f"{tr.path}: no truth channel (/{tr.machine}/{tr.axis}/truth); use a trial written by "
                         "feedmon simulate")
    force = tr.truth.force * scale
    bad = np.flatnonzero(~np.isfinite(force))
    if bad.size:
        raise ValueError(f"{tr.path}: the truth force is missing or not finite at {bad.size} sample(s), first at "
                         f"sample {int(bad[0])}; halstreamer needs a value for every cycle")
    np.savetxt(output, force, fmt="%.17g")
    return int(force.size)
