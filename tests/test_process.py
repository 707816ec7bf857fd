"""kernels.process and kernels.blocks: where a process acts, and the likelihood of a disturbance gated to it."""

import numpy as np
import pytest
from reml_reference import dense_gls_cov, dense_reml
from scipy.linalg import block_diag

from feedio.mcapio import read_trial
from kernels.blocks import blocks
from kernels.covariance import LocallyPeriodic
from kernels.errors import ParameterError
from kernels.likelihood import reml_terms
from kernels.pl_lssvm import pl_lssvm
from kernels.process import process_mask
from monitor.identify.regression import build_regression
from replay.streams import shaker_stream


@pytest.mark.parametrize("scenario", ["shaker-constant", "milling-incdec", "shaker-control", "milling-aircut"])
def test_the_mask_is_where_the_simulated_process_acts(simulated, scenario):
    """From the LS residual alone: the shaker (on for the middle half) and the cut (after the lead-in) within
    a few percent of the samples; nothing on the control trial (its reversals' transients are no process)
    and on the air cut."""
    trial = read_trial(simulated(scenario, seed=5, duration=20.0))
    form = trial.meta.form
    reg = build_regression(form, trial.v_meas, trial.v_ref, trial.meta.Ts, omega=None, coulomb=None,
                           spindle_rpm=trial.spindle_rpm, notes=[])
    acting = np.abs(trial.truth.force[:-1]) > 0.0
    found = reg.process.active
    assert np.mean(found != acting) < 0.02, (found.mean(), acting.mean())
    if acting.any():
        assert reg.nuisance[:2] == ("process", "process*v_meas") and reg.offset_separated is True
    else:
        assert reg.nuisance == () and reg.offset_separated is True


def test_a_process_that_never_stops_while_the_axis_moves_is_said_to_hold_the_offset(simulated):
    """No motion without the process (the lead-in shortened to nothing): its mean force cannot be told from
    friction and offset — no nuisance columns, offset_separated False, and a note that says so."""
    from replay.scenarios import load_scenario
    from replay.simulator import simulate

    sc = load_scenario("milling-inc", {"trajectory": {"lead_in": 0.02, "lead_out": 0.02},
                                       "disturbance": {"entry": 0.001}}, duration=10.0)
    res = simulate(sc, seed=2)
    notes = []
    reg = build_regression("velocity-loop", res.v_meas, res.v_ref, 1 / 333, omega=None, coulomb=None,
                           spindle_rpm=res.spindle_rpm, notes=notes)
    assert reg.offset_separated is False and reg.nuisance == ()
    assert any("cannot be told from friction and offset" in n for n in notes)


def test_the_gated_likelihood_is_the_dense_reml_of_its_covariance():
    """Eq. B1: A = g gᵀ ∘ K + γ⁻¹I, the correlation across a closed stretch left out; the REML, the GLS
    covariance and the PL-LSSVM β equal the dense reference of that block matrix; where the gate is closed
    the disturbance estimate is the constant."""
    s = shaker_stream(601, amplitude=10.0, seed=21)
    reg = s.regression()
    kernel, gamma = LocallyPeriodic(0.3, 0.5, 1 / 55), 80.0
    gate = np.zeros(600, dtype=bool)
    gate[150:420] = True
    A = block_diag(np.eye(150) / gamma, kernel(np.arange(270) * s.Ts) + np.eye(270) / gamma, np.eye(180) / gamma)
    terms = reml_terms(reg.Z, reg.y, kernel, gamma, s.Ts, gate=gate)
    assert terms.solver == "gated-1"
    assert terms.log_likelihood == pytest.approx(dense_reml(reg.Z, reg.y, A), rel=1e-9)
    np.testing.assert_allclose(terms.cov, dense_gls_cov(reg.Z, reg.y, A), rtol=1e-7)
    fit = pl_lssvm(reg.Z, reg.y, kernel, gamma, Ts=s.Ts, gate=gate, solver="levinson")
    np.testing.assert_allclose(fit.beta, terms.beta, rtol=1e-7)
    np.testing.assert_allclose(fit.f[~gate], fit.c, atol=1e-12)
    parts = blocks(kernel, gamma, s.Ts, 600, gate=gate)
    assert [(b.start, b.stop, b.column is None) for b in parts] == [(0, 150, True), (150, 420, False), (420, 600, True)]


def test_samples_left_out_carry_nothing():
    """``keep`` False: the REML and β are those of the kept samples alone, the correlation across the gap left
    out (two independent stretches); LS likewise; the disturbance is not estimated there (NaN)."""
    s = shaker_stream(601, amplitude=10.0, seed=22)
    reg = s.regression()
    kernel, gamma = LocallyPeriodic(0.3, 0.5, 1 / 55), 80.0
    keep = np.ones(600, dtype=bool)
    keep[200:260] = False
    Z, y = reg.Z[keep], reg.y[keep]
    A = block_diag(kernel(np.arange(200) * s.Ts) + np.eye(200) / gamma,
                   kernel(np.arange(340) * s.Ts) + np.eye(340) / gamma)
    terms = reml_terms(reg.Z, reg.y, kernel, gamma, s.Ts, keep=keep)
    assert terms.n == 540
    assert terms.log_likelihood == pytest.approx(dense_reml(Z, y, A), rel=1e-9)
    ls = reml_terms(reg.Z, reg.y, None, None, s.Ts, keep=keep)
    assert ls.log_likelihood == pytest.approx(dense_reml(Z, y, np.eye(540)), rel=1e-9)
    fit = pl_lssvm(reg.Z, reg.y, kernel, gamma, Ts=s.Ts, keep=keep, solver="levinson")
    np.testing.assert_allclose(fit.beta, terms.beta, rtol=1e-7)
    assert np.all(np.isnan(fit.f[~keep])) and np.all(np.isfinite(fit.f[keep]))


def test_bad_inputs_name_the_parameter():
    with pytest.raises(ParameterError) as exc:
        process_mask(np.ones(100), 0.0, 0.9, 0.003)
    assert exc.value.parameters == ("sigma_n",)
    with pytest.raises(ParameterError) as exc:
        process_mask(np.ones(100), 1e-6, 0.9, 0.003, idle=np.ones(5, dtype=bool))
    assert exc.value.parameters == ("idle",)
    with pytest.raises(ValueError, match="gate mask has 5 samples"):
        blocks(LocallyPeriodic(0.3, 0.5, 0.02), 10.0, 0.003, 10, gate=np.ones(5, dtype=bool))
