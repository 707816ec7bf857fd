"""kernels.feed_drive: β ↔ physical round trips, regressors, free run, force conversion (method §1–2, §6)."""

import numpy as np
import pytest

from kernels.feed_drive import (
    beta_names,
    beta_to_physical,
    disturbance_to_force,
    force_to_disturbance,
    physical_to_beta,
    regressors,
    simulate_free_run,
)

try:
    from tests.streams import GAIN, TS, shaker_stream, simulate
except ImportError:  # tests/ not a package
    from streams import GAIN, TS, shaker_stream, simulate

PHYS = dict(inertia=120.0, damping=85.0, coulomb_pos=18.0, coulomb_neg=23.0)


@pytest.mark.parametrize("coulomb", [True, False])
def test_velocity_loop_round_trip_with_gain(coulomb):
    beta = physical_to_beta("velocity-loop", TS, gain=GAIN, coulomb=coulomb, **PHYS)
    assert beta.shape == (4 if coulomb else 2,)
    phys = beta_to_physical("velocity-loop", beta, TS, gain=GAIN, coulomb=coulomb)
    assert phys.inertia == pytest.approx(PHYS["inertia"], rel=1e-10)
    assert phys.damping == pytest.approx(PHYS["damping"], rel=1e-10)
    if coulomb:
        assert phys.coulomb_pos == pytest.approx(PHYS["coulomb_pos"], rel=1e-10)
        assert phys.coulomb_neg == pytest.approx(PHYS["coulomb_neg"], rel=1e-10)
    else:
        assert phys.coulomb_pos is None and phys.coulomb_neg is None
    again = physical_to_beta("velocity-loop", TS, phys.inertia, phys.damping, gain=GAIN, coulomb=coulomb,
                             coulomb_pos=phys.coulomb_pos or 0.0, coulomb_neg=phys.coulomb_neg or 0.0)
    np.testing.assert_allclose(again, beta, rtol=1e-12)


@pytest.mark.parametrize("coulomb", [True, False])
def test_velocity_loop_without_gain_gives_ratios(coulomb):
    beta = physical_to_beta("velocity-loop", TS, gain=GAIN, coulomb=coulomb, **PHYS)
    phys = beta_to_physical("velocity-loop", beta, TS, coulomb=coulomb)
    assert phys.inertia is None and phys.damping is None and phys.gain is None
    assert phys.inertia_over_gain == pytest.approx(PHYS["inertia"] / GAIN, rel=1e-10)
    assert phys.damping_over_gain == pytest.approx(PHYS["damping"] / GAIN, rel=1e-10)
    if coulomb:
        assert phys.coulomb_pos_over_gain == pytest.approx(PHYS["coulomb_pos"] / GAIN, rel=1e-10)
        assert phys.coulomb_neg_over_gain == pytest.approx(PHYS["coulomb_neg"] / GAIN, rel=1e-10)
    assert "inertia" not in phys.to_dict()


@pytest.mark.parametrize("coulomb", [True, False])
def test_force_input_round_trip(coulomb):
    beta = physical_to_beta("force-input", TS, offset=3.5, coulomb=coulomb, **PHYS)
    assert beta.shape == (5 if coulomb else 3,)
    phys = beta_to_physical("force-input", beta, TS, coulomb=coulomb)
    assert phys.inertia == pytest.approx(PHYS["inertia"], rel=1e-10)
    assert phys.damping == pytest.approx(PHYS["damping"], rel=1e-10)
    assert phys.offset == pytest.approx(3.5, rel=1e-10)
    if coulomb:
        assert phys.coulomb_pos == pytest.approx(PHYS["coulomb_pos"], rel=1e-10)
        assert phys.coulomb_neg == pytest.approx(PHYS["coulomb_neg"], rel=1e-10)


def test_thesis_case1_beta():
    beta = physical_to_beta("velocity-loop", TS, 100.0, 100.0, gain=GAIN)
    assert beta[0] == pytest.approx(0.834, rel=1e-12)
    assert beta[1] == pytest.approx(0.163, abs=1e-3)


def test_beta_to_physical_rejects_unstable():
    with pytest.raises(ValueError, match="0 < p_d < 1"):
        beta_to_physical("velocity-loop", [0.5, 0.6, 0.0, 0.0], TS, gain=GAIN)
    with pytest.raises(ValueError, match="entries"):
        beta_to_physical("force-input", [0.5, 0.6], TS)
    with pytest.raises(ValueError, match="loop gain"):
        physical_to_beta("velocity-loop", TS, 1.0, 1.0)
    with pytest.raises(ValueError, match="not known"):
        physical_to_beta("torque", TS, 1.0, 1.0)


@pytest.mark.parametrize("form,coulomb,m", [("velocity-loop", True, 4), ("velocity-loop", False, 2),
                                            ("force-input", True, 5), ("force-input", False, 3)])
def test_regressors_shapes_and_names(form, coulomb, m):
    n = 50
    v = np.linspace(-0.1, 0.1, n)
    kw = {"v_ref": v * 1.1} if form == "velocity-loop" else {"u": v * 300.0}
    reg = regressors(form, v, omega=0.01, coulomb=coulomb, **kw)
    assert reg.Z.shape == (n - 1, m)
    assert reg.y.shape == (n - 1,)
    assert reg.names == beta_names(form, coulomb)
    np.testing.assert_array_equal(reg.y, v[1:])
    np.testing.assert_array_equal(reg.Z[:, 1], v[:-1])
    if coulomb:
        np.testing.assert_array_equal(reg.Z[:, 2], -(v[:-1] > 0.01).astype(float))
        np.testing.assert_array_equal(reg.Z[:, 3], -(v[:-1] < -0.01).astype(float))
    if form == "force-input":
        np.testing.assert_array_equal(reg.Z[:, -1], 1.0)
        assert reg.names[-1] == "one"


def test_regressors_errors():
    v = np.zeros(20)
    with pytest.raises(ValueError, match="v_ref has 19 samples but v_meas has 20"):
        regressors("velocity-loop", v, v_ref=np.zeros(19))
    bad = v.copy()
    bad[7] = np.nan
    with pytest.raises(ValueError, match="v_ref has 1 non-finite value.*sample 7"):
        regressors("velocity-loop", v, v_ref=bad)
    with pytest.raises(ValueError, match="v_meas has 1 non-finite value.*sample 7"):
        regressors("velocity-loop", bad, v_ref=v)
    with pytest.raises(ValueError, match="u has 1 non-finite"):
        regressors("force-input", v, u=bad)
    with pytest.raises(ValueError, match="needs v_ref"):
        regressors("velocity-loop", v)
    with pytest.raises(ValueError, match="needs u"):
        regressors("force-input", v, v_ref=v)
    with pytest.raises(ValueError, match="dead band"):
        regressors("velocity-loop", v, v_ref=v, omega=-1.0)


@pytest.mark.parametrize("form", ["velocity-loop", "force-input"])
def test_free_run_equals_generating_recursion(form):
    kw = {"offset": 2.0} if form == "force-input" else {}
    s = shaker_stream(1500, amplitude=10.0, noise=0.0, seed=3, form=form, **kw)
    v_hat = simulate_free_run(form, s.beta, s.v_meas[0], s.exogenous, omega=s.omega, coulomb=True,
                              disturbance=np.append(s.f, 0.0))
    np.testing.assert_allclose(v_hat, s.v_meas, rtol=1e-10, atol=1e-14)


def test_free_run_without_disturbance_matches_noise_free_stream():
    s = simulate(800, noise=0.0, seed=5, coulomb=False)
    v_hat = simulate_free_run("velocity-loop", s.beta, 0.0, s.exogenous, coulomb=False)
    np.testing.assert_allclose(v_hat, s.v_meas, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("form,gain", [("velocity-loop", GAIN), ("force-input", None)])
def test_force_disturbance_inverse(form, gain):
    beta = physical_to_beta(form, TS, gain=gain, **PHYS)
    force = np.random.default_rng(0).normal(0, 30.0, 200)
    f = force_to_disturbance(form, beta, force, gain=gain)
    np.testing.assert_allclose(disturbance_to_force(form, beta, f, gain=gain), force, rtol=1e-12)
    b = (1 - np.exp(-PHYS["damping"] * TS / PHYS["inertia"])) / PHYS["damping"]
    np.testing.assert_allclose(f, -b * force, rtol=1e-10)


def test_velocity_loop_force_needs_gain():
    beta = physical_to_beta("velocity-loop", TS, gain=GAIN, **PHYS)
    with pytest.raises(ValueError, match="loop gain"):
        disturbance_to_force("velocity-loop", beta, np.zeros(3))
