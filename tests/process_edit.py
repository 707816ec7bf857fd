"""Process events put into a simulated velocity-loop trial after the fact, for the process monitors' tests.

The simulated plant is linear in the disturbance force (method §1): a force ``ΔF(k)`` (N) acting over
sample interval ``k`` changes the measured velocity by ``Δv(k+1) = β2·Δv(k) − b·ΔF(k)`` with
``b = β1/K`` (velocity loop, ``β2 = p_d − K_d``), whatever else acts. Adding that response to ``v_meas``
gives the trial the simulator would have made with the extra force (up to the Coulomb term, which the
milling scenarios do not have)."""

from __future__ import annotations

import msgspec
import numpy as np
from trial_edit import rewrite_samples

from feedio.mcapio import read_trial


def add_force(src, dst, delta_force: np.ndarray, *, context: dict[str, np.ndarray] | None = None):
    """``src`` with the extra force ``delta_force`` (N per sample, length of the trial) in its velocities and
    the context columns ``context`` (``program_line``, ``tool``: int per sample) added; returns ``dst``."""
    meta = read_trial(src).meta
    beta = meta.truth.beta
    b = beta[0] / meta.loop_gain
    n = delta_force.size
    dv = np.zeros(n)
    for k in range(n - 1):
        dv[k + 1] = beta[1] * dv[k] - b * delta_force[k]

    def edit(block):
        i0, m = block.seq, len(block.t)
        v = np.array(block.v_meas, dtype=np.float64) + dv[i0:i0 + m]
        extra = {k: [int(x) for x in c[i0:i0 + m]] for k, c in (context or {}).items()}
        return msgspec.structs.replace(block, v_meas=v.tolist(), **extra)

    return rewrite_samples(src, dst, edit)


def tooth_share_force(theta: np.ndarray, cut_force: np.ndarray, lost: float, teeth: int = 2) -> np.ndarray:
    """The force change (N) when tooth 0 loses the fraction ``lost`` of its chip to the next tooth: tooth 0's
    sector (``θ mod 2π`` in its ``2π/N_t``) loses ``lost·F``, the next sector gains it."""
    sector = ((theta % (2 * np.pi)) // (2 * np.pi / teeth)).astype(int)
    return np.where(sector == 0, -lost * cut_force, np.where(sector == 1, lost * cut_force, 0.0))
