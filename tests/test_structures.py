"""replay.plant: drives the rigid model does not describe, and what identify makes of the Stribeck drive."""

import math

import numpy as np
import pytest

from feedio.mcapio import read_trial
from kernels.errors import ParameterError
from monitor.identify import identify
from replay.plant import Structure, closed_loop_radius, structured_loop
from replay.scenarios import load_scenario
from replay.simulator import SimulationError, UnstableLoopError, closed_loop_zoh, simulate

TS = 1 / 333


def test_the_rigid_structure_is_the_exact_zoh_plant():
    """Without a resonance, a delay, an encoder or Stribeck friction the structured loop (state space, matrix
    exponential) is the simulator's exact ZOH loop, sample for sample."""
    rng = np.random.default_rng(2)
    n = 3000
    v_ref = np.repeat(rng.uniform(-0.1, 0.1, 30), 100)
    tc = 20 * np.sin(2 * np.pi * 55 * np.arange(n) * TS)
    noise = rng.normal(0, 5e-6, n)
    a = closed_loop_zoh(v_ref, tc, noise, TS, 300.0, 300.0, 83300.0, 9.0, 10.0, 5e-4)
    b = structured_loop(Structure(), v_ref, tc, noise, TS, 300.0, 300.0, 83300.0, 9.0, 10.0, 5e-4)
    for x, y in zip(a[:4], b):
        np.testing.assert_allclose(y, x, rtol=1e-9, atol=1e-12)


def test_closed_loop_radius_and_refusal():
    """The rigid loop's pole is p_d − K_d (method §1); a structure whose loop diverges is refused before anything
    is simulated, naming what to change."""
    p_d = math.exp(-300.0 * TS / 300.0)
    K_d = 83300.0 * (1 - p_d) / 300.0
    assert closed_loop_radius(Structure(), TS, 300.0, 300.0, 83300.0) == pytest.approx(abs(p_d - K_d), rel=1e-9)
    assert closed_loop_radius(Structure(delay=2), TS, 300.0, 300.0, 83300.0) > 1.0
    sc = load_scenario("command-delay", {"structure": {"delay": 2}, "drive": {"loop_gain": 83300.0}}, duration=2.0)
    with pytest.raises(UnstableLoopError, match="the force acts 2 sample"):
        simulate(sc)
    with pytest.raises(ParameterError, match="fine=True simulates the rigid drive only") as exc:
        simulate(load_scenario("two-mass", duration=1.0), fine=True)
    assert exc.value.parameters == ("fine",)
    with pytest.raises(SimulationError, match="drive_drift and drive_step need the rigid drive"):
        simulate(load_scenario("two-mass", {"drive_drift": {"inertia": 0.1}}, duration=1.0))
    with pytest.raises(ValueError, match="structure.kind must be one of"):
        load_scenario("two-mass", {"structure": {"kind": "three-mass"}})


def test_an_encoder_velocity_is_the_backward_difference_of_the_quantised_position():
    sc = load_scenario("encoder-velocity", duration=3.0)
    res = simulate(sc, seed=1)
    q = 1e-8 * np.floor(res.position / 1e-8 + 0.5)
    np.testing.assert_allclose(res.v_meas[1:], np.diff(q) / TS, rtol=1e-9, atol=1e-12)


def test_the_stribeck_drive_is_identified_within_tolerance(simulated):
    """Issue check: Stribeck friction at low speed (35 → 50 N under 2 mm/s, slow sines): J, B within 2 %, Fc
    within 5 % (least squares on all samples: B −16 %). The samples below the speed where the law holds again,
    found in the data, are left out and the monitor learns β only above it."""
    ident = identify(read_trial(simulated("drive-stribeck", seed=4, duration=40.0)))
    truth = ident.truth["physical"]
    phys = ident.model_result.physical
    assert phys["inertia"] == pytest.approx(truth["inertia"], rel=0.02)
    assert phys["damping"] == pytest.approx(truth["damping"], rel=0.02)
    assert phys["coulomb"] == pytest.approx(truth["coulomb"], rel=0.05)
    checks = ident.checks
    assert checks["left_out"] > 0 and checks["law_holds_above"]["rise"]
    assert 0.002 < checks["law_holds_above"]["speed"] < 0.008 and ident.min_speed >= checks["law_holds_above"]["speed"]
    assert any("a Stribeck rise — those samples are left out of the batch fit" in n for n in ident.notes)
    assert ident.adequacy.adequate
