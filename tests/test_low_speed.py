"""The low-speed friction check (kernels/low_speed.py, eq. LS1–LS2): a regression of a force-input drive
whose friction near standstill departs from the Coulomb + viscous law, built from the exact model, with
the departure known; and the online β's gate that it sets (no learning at or below ``min_speed``)."""

import numpy as np
import pytest

from kernels import KRLST, LocallyPeriodic
from kernels.beta_tracker import C_UPDATES, OnlineBeta
from kernels.feed_drive import regressors
from kernels.low_speed import LowSpeedFriction, low_speed_friction

TS = 1 / 333
OMEGA = 5e-4


def _drive(*, hump_n: float, v_s: float, vmax: float = 0.12, period: float = 4.0, seed: int = 0, n: int = 8000):
    """A force-input drive (J 95 kg, B 200 N·s/m, Fc 20 N) following a smooth reversing trajectory; the
    friction near standstill is ``hump_n · exp(−(v/v_s)²)`` N above the law (0: the law holds).
    Returns (Z, y, v, b): regressors, targets, the velocity the rows use, the input gain."""
    rng = np.random.default_rng(seed)
    J, B, Fc = 95.0, 200.0, 20.0
    p = np.exp(-B * TS / J)
    b = (1 - p) / B
    t = np.arange(n) * TS
    v_target = vmax * np.sin(2 * np.pi * t / period)              # reverses every period/2
    v = np.zeros(n)
    u = np.zeros(n)
    for k in range(n - 1):
        u[k] = 4000.0 * (v_target[k + 1] - v[k]) + B * v[k] + Fc * np.sign(v[k])
        sgn = np.sign(v[k]) if abs(v[k]) > OMEGA else 0.0
        fric = Fc * sgn + hump_n * sgn * np.exp(-((v[k] / v_s) ** 2))
        v[k + 1] = p * v[k] + b * (u[k] - fric) + 2e-5 * rng.standard_normal()
    reg = regressors("force-input", v, u=u, omega=OMEGA, coulomb=True, intercept=True)
    return reg.Z, reg.y, v[:-1], b


def _ls_error(Z, y):
    beta, *_ = np.linalg.lstsq(Z, y, rcond=None)
    return y - Z @ beta


@pytest.mark.parametrize("hump_n", [-6.0, 8.0])
def test_a_departure_near_standstill_is_found_with_its_size_and_speed(hump_n):
    Z, y, v, b = _drive(hump_n=hump_n, v_s=0.01)
    check = low_speed_friction(Z, _ls_error(Z, y), v, OMEGA)
    assert isinstance(check, LowSpeedFriction)
    assert check.significant and check.local and check.gain > 100
    assert 0.006 <= check.v_s <= 0.016                       # the scan's best scale: the true 0.01 within its grid
    assert check.amplitude / b == pytest.approx(hump_n, rel=0.3)
    assert check.min_speed == pytest.approx(2 * check.v_s)


def test_the_law_holding_gives_no_gate():
    Z, y, v, _ = _drive(hump_n=0.0, v_s=0.01)
    check = low_speed_friction(Z, _ls_error(Z, y), v, OMEGA)
    assert check is not None and not check.significant and check.min_speed == 0.0


def test_an_effect_over_most_of_the_motion_is_reported_not_gated():
    """A 'hump' wider than most of the record's speeds is not a low-speed effect: gating it would
    stop the learning."""
    Z, y, v, _ = _drive(hump_n=8.0, v_s=0.1, vmax=0.06)
    check = low_speed_friction(Z, _ls_error(Z, y), v, OMEGA)
    assert check.significant and not check.local and check.share > 0.25 and check.min_speed == 0.0


def test_nothing_to_test_and_bad_input():
    Z, y, v, _ = _drive(hump_n=0.0, v_s=0.01, n=400)
    assert low_speed_friction(Z, _ls_error(Z, y), np.zeros_like(v), OMEGA) is None      # never moving
    with pytest.raises(ValueError, match="same number of rows"):
        low_speed_friction(Z, y[:-1], v, OMEGA)
    bad = y.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        low_speed_friction(Z, bad, v, OMEGA)


def test_online_beta_learns_nothing_at_or_below_min_speed():
    """The gate: the same stream, β learns with min_speed 0 and not at all with a min_speed above
    every speed of the stream; a min_speed out of its range is refused."""
    Z, y, v, b = _drive(hump_n=0.0, v_s=0.01, n=1500)
    beta0, *_ = np.linalg.lstsq(Z, y, rcond=None)
    names = ("u", "v_meas", "-sigma_p", "-sigma_n", "one")
    updates = {}
    for min_speed in (0.0, 1.0):
        ob = OnlineBeta(KRLST(LocallyPeriodic(1.2, 0.5, 1.0), gamma=300.0, forgetting=0.998, budget=50),
                        beta0, names, TS, omega=OMEGA, warmup=50, min_speed=min_speed)
        for k in range(len(y)):
            ob.predict_one(np.array([k * TS]))
            ob.learn_one(Z[k], y[k])
        updates[min_speed] = int(ob.state.cnt[C_UPDATES])
    assert updates[0.0] > 500 and updates[1.0] == 0
    with pytest.raises(ValueError, match="min_speed"):
        OnlineBeta(KRLST(LocallyPeriodic(1.2, 0.5, 1.0), gamma=300.0, forgetting=0.998, budget=50),
                   beta0, names, TS, omega=OMEGA, min_speed=-1.0)

