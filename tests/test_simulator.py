"""Simulator with known truth: exact ZOH truth, physics sanity, determinism, CLI, speed."""

import time

import numpy as np
import pytest

from feedio.mcapio import read_trial
from feedmon.cli import main
from kernels.feed_drive import force_to_disturbance, physical_to_beta, regressors
from kernels.least_squares import least_squares
from replay import scenarios as SC
from replay.cutting import MillingTool, feed_force, mean_feed_force
from replay.simulator import (
    SimulationError,
    UnstableLoopError,
    closed_loop_zoh,
    simulate_scenario,
    true_beta,
    write_trial,
)

QUIET = {"noise": {"v_meas_std": 0.0, "glitch_rate": 0.0, "dynamometer_std": 0.0}}


def _ls(trial_like):
    truth = trial_like.meta.truth
    reg = regressors(trial_like.meta.form, trial_like.v_meas, v_ref=trial_like.v_ref, omega=truth.omega,
                     coulomb=truth.coulomb)
    return reg, least_squares(reg.Z, reg.y).beta


@pytest.mark.parametrize("name", ["shaker-control", "milling-aircut"])
def test_ls_recovers_true_beta_noise_free(name, tmp_path):
    res = simulate_scenario(name, seed=0, duration=20.0, config=QUIET)
    p = tmp_path / "q.mcap"
    write_trial(res, p)
    tr = read_trial(p)
    beta = np.array(tr.meta.truth.beta)
    phys = tr.meta.truth.physical
    expect = physical_to_beta(
        "velocity-loop", tr.Ts, phys["inertia"], phys["damping"], gain=phys["loop_gain"],
        coulomb_pos=phys["coulomb_pos"], coulomb_neg=phys["coulomb_neg"], coulomb=tr.meta.truth.coulomb,
    )
    np.testing.assert_array_equal(beta, expect)
    assert tr.meta.loop_gain == phys["loop_gain"]
    _, b = _ls(tr)
    assert b.shape == beta.shape == ((4,) if name == "shaker-control" else (2,))
    np.testing.assert_allclose(b, beta, rtol=1e-9, atol=0)


def test_thesis_like_beta():
    b1 = true_beta(SC.load_scenario("shaker-constant"))
    assert b1[0] == pytest.approx(0.834, abs=0.003) and b1[1] == pytest.approx(0.163, abs=0.003)
    assert 5e-5 < abs(b1[2]) < 2e-4 and 5e-5 < abs(b1[3]) < 2e-4
    b2 = true_beta(SC.load_scenario("milling-incdec"))
    assert b2[0] == pytest.approx(0.37, abs=0.005) and b2[1] == pytest.approx(0.63, abs=0.005)


def test_truth_is_the_model_residual():
    """Noise-free with a disturbance: y − Zβ equals the recorded f = −b·T_c exactly."""
    res = simulate_scenario("shaker-constant", seed=0, duration=10.0, config=QUIET)
    reg, _ = _ls(res)
    resid = reg.y - reg.Z @ res.beta
    np.testing.assert_allclose(resid, res.f[:-1], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(res.f, force_to_disturbance("velocity-loop", res.beta, res.force, gain=res.meta.loop_gain))
    on = res.force != 0
    assert on.any() and not on[: int(0.24 * len(res))].any() and not on[int(0.76 * len(res)):].any()
    assert np.abs(res.force).max() > 50.0


def test_disturbance_biases_ls():
    res = simulate_scenario("shaker-constant", seed=0)
    _, b = _ls(res)
    assert abs(b[0] / res.beta[0] - 1) > 0.005  # visibly biased (PL-LSSVM's job to remove)
    res = simulate_scenario("milling-incdec", seed=0)
    _, b = _ls(res)
    assert abs(b[0] / res.beta[0] - 1) > 0.2


def test_milling_force_spectrum_and_feed_dependence():
    tool = MillingTool()
    Ts = 1 / 333
    n = 3330
    F = feed_force(tool, 0.0, Ts, np.full(n, 0.006))
    spec = np.abs(np.fft.rfft(F - F.mean()))
    freq = np.fft.rfftfreq(n, Ts)

    def line(f0):
        k = np.argmin(np.abs(freq - f0))
        return spec[k - 2:k + 3].max()

    floor = np.median(spec)
    assert line(50.0) > 20 * floor and line(100.0) > 20 * floor
    assert line(100.0) > line(50.0)  # tooth passing dominates, runout adds the spindle line
    # mean force grows with the feed rate and matches the closed form (no runout)
    no_runout = MillingTool(runout=0.0)
    feeds = [0.002, 0.006, 0.010]
    means = [feed_force(no_runout, 0.0, Ts, np.full(n, v)).mean() for v in feeds]
    assert means[0] < means[1] < means[2]
    for v, m in zip(feeds, means):
        assert m == pytest.approx(mean_feed_force(no_runout, v), rel=2e-3)
    # in a simulated trial too: the truth channel follows the feed steps
    res = simulate_scenario("milling-inc", seed=0)
    levels = [c * 1e-3 * 100.0 for c in SC.load_scenario("milling-inc")["trajectory"]["levels"]]  # mm/tooth → m/s
    assert res.spindle_rpm is not None and res.meta.teeth == 2 and res.meta.spindle_rpm == 3000.0
    steady = [res.force[np.isclose(res.v_ref, v) & (res.t > 1.0) & (res.t < res.t[-1] - 1.0)].mean() for v in levels]
    assert np.all(np.diff(steady) > 0)
    assert np.allclose(res.dynamometer, -res.force, atol=10.0)  # sensor noise only


def test_glitches_repeat_previous_value():
    res = simulate_scenario("milling-incdec", seed=3, config={"noise": {"glitch_rate": 0.01}})
    g = np.flatnonzero(res.glitch)
    assert g.size > 50 and not res.glitch[0]
    np.testing.assert_array_equal(res.v_meas[g], res.v_meas[g - 1])
    assert res.meta.truth.coulomb is False


def test_fine_path_close_to_nominal_beta():
    res = simulate_scenario("shaker-control", seed=0, duration=20.0, fine=True)
    _, b = _ls(res)
    assert res.meta.provenance.details["fine"] is True
    np.testing.assert_allclose(b[:2], res.beta[:2], rtol=0.05)  # not exact (AA filter, continuous friction)


def test_config_overrides_and_errors(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[drive]\ninertia = 600.0\n[disturbance]\namplitude = 5.0\n")
    sc = SC.load_scenario("shaker-constant", cfg)
    assert sc["drive"]["inertia"] == 600.0 and sc["disturbance"]["amplitude"] == 5.0
    bad = tmp_path / "bad.toml"
    bad.write_text("[drive]\ninertya = 1.0\n")
    with pytest.raises(ValueError, match="unknown scenario key 'drive.inertya'"):
        SC.load_scenario("shaker-constant", bad)
    with pytest.raises(ValueError, match="drive.damping must be a finite number > 0"):
        SC.load_scenario("shaker-constant", {"drive": {"damping": -1.0}})
    with pytest.raises(ValueError, match="unknown scenario 'nope'"):
        SC.load_scenario("nope")


def test_cli_simulate(tmp_path, capsys):
    out = tmp_path / "cli.mcap"
    assert main(["simulate", "milling-dec", "-o", str(out), "--seed", "4", "--duration", "3"]) == 0
    tr = read_trial(out)
    assert tr.meta.provenance.seed == 4 and tr.meta.provenance.scenario == "milling-dec" and len(tr) == 999
    assert tr.meta.provenance.created is None
    bad = tmp_path / "bad.toml"
    bad.write_text("[noise]\nglitch_rate = 2.0\n")
    assert main(["simulate", "milling-dec", "-o", str(out), "--config", str(bad)]) == 2
    assert "glitch_rate" in capsys.readouterr().err


def test_ten_minute_trial_speed(tmp_path):
    simulate_scenario("shaker-sweep", duration=1.0)  # numba cache warm-up
    t0 = time.perf_counter()
    res = simulate_scenario("shaker-sweep", duration=600.0)
    t1 = time.perf_counter()
    write_trial(res, tmp_path / "long.mcap")
    t2 = time.perf_counter()
    print(f"\n10-minute shaker-sweep trial: simulate {t1 - t0:.2f} s, write MCAP {t2 - t1:.2f} s, {len(res)} samples")
    assert len(res) == 199800


# ---------------------------------------------------------------------------------------------
# refusing what cannot be a trial
# ---------------------------------------------------------------------------------------------
WEAK = {"drive": {"inertia": 60.0, "damping": 60.0}}  # the shaker drive at 0.2×, default loop gain


def _pole_and_limit(J, B, K, Ts):
    p_d = np.exp(-B * Ts / J)
    return p_d - K * (1 - p_d) / B, B * (1 + p_d) / (1 - p_d)


@pytest.mark.parametrize("fine", [False, True])
def test_unstable_loop_is_refused_naming_the_pole(fine):
    sc = SC.load_scenario("shaker-constant", WEAK)
    Ts, K = 1 / sc["rate"], sc["drive"]["loop_gain"]
    pole, k_max = _pole_and_limit(60.0, 60.0, K, Ts)
    assert pole < -1
    with pytest.raises(UnstableLoopError) as exc:
        simulate_scenario("shaker-constant", duration=2.0, config=WEAK, fine=fine)
    msg = str(exc.value)
    assert f"p_d − K_d = {pole:.6g}" in msg and f"loop_gain < {k_max:.6g} N·s/m" in msg
    assert ("10 kHz fine path (30 substeps" in msg) == fine and ("exact-ZOH loop" in msg) != fine
    # the stable range it names is right: just inside runs (and rings down), just outside is refused
    inside = {"drive": dict(WEAK["drive"], loop_gain=0.98 * k_max)}
    res = simulate_scenario("shaker-constant", duration=2.0, config=inside, fine=fine)
    assert np.all(np.isfinite(res.v_meas)) and np.abs(res.v_true).max() < 1.0
    outside = {"drive": dict(WEAK["drive"], loop_gain=1.02 * k_max)}
    with pytest.raises(UnstableLoopError):
        simulate_scenario("shaker-constant", duration=2.0, config=outside, fine=fine)


def test_unstable_after_a_drive_step_names_the_time():
    cfg = {"drive_step": {"at": 0.5, "inertia": -0.8, "damping": -0.8}}
    with pytest.raises(UnstableLoopError, match=r"from t = 1 s \(sample 333; the drive constants vary"):
        simulate_scenario("shaker-constant", duration=2.0, config=cfg)
    with pytest.raises(UnstableLoopError, match="unstable closed loop"):
        closed_loop_zoh(np.zeros(10), np.zeros(10), np.zeros(10), 1 / 333, 60.0, 60.0, 83300.0, 9.0, 10.0, 5e-4)


def test_closed_loop_zoh_constants_scalar_or_per_sample():
    rng = np.random.default_rng(0)
    v_ref = np.repeat([0.0, 0.05, -0.05, 0.0], 50)
    tc, noise = rng.normal(0, 5, v_ref.size), rng.normal(0, 1e-6, v_ref.size)
    a = closed_loop_zoh(v_ref, tc, noise, 1 / 333, 300.0, 300.0, 83300.0, 9.0, 10.0, 5e-4)
    n = v_ref.size
    b = closed_loop_zoh(v_ref, tc, noise, 1 / 333, np.full(n, 300.0), np.full(n, 300.0), 83300.0,
                        np.full(n, 9.0), np.full(n, 10.0), 5e-4)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)  # one compiled loop, run twice
    J = np.where(np.arange(n) < 100, 300.0, 600.0)
    c = closed_loop_zoh(v_ref, tc, noise, 1 / 333, J, 300.0, 83300.0, 9.0, 10.0, 5e-4)
    np.testing.assert_array_equal(c[0][:101], a[0][:101])  # v(100) is set by J(99)
    assert not np.array_equal(c[0][101:], a[0][101:])
    with pytest.raises(SimulationError, match="finite inertia > 0"):
        closed_loop_zoh(v_ref, tc, noise, 1 / 333, np.where(J > 400, np.nan, J), 300.0, 83300.0, 9.0, 10.0, 5e-4)
    with pytest.raises(ValueError, match="J has shape"):
        closed_loop_zoh(v_ref, tc, noise, 1 / 333, J[:5], 300.0, 83300.0, 9.0, 10.0, 5e-4)


@pytest.mark.parametrize(("amplitude", "fine"), [(float("inf"), False), (float("nan"), True), (1e300, False)])
def test_non_finite_or_absurd_samples_are_never_written(amplitude, fine):
    with pytest.raises(SimulationError, match="nothing written") as exc:
        simulate_scenario("shaker-constant", duration=2.0, config={"disturbance": {"amplitude": amplitude}}, fine=fine)
    assert "non-finite or beyond" in str(exc.value)


def test_cli_refuses_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "never.mcap"
    cfg = tmp_path / "weak.toml"
    cfg.write_text("[drive]\ninertia = 60.0\ndamping = 60.0\n")
    assert main(["simulate", "shaker-constant", "-o", str(out), "--config", str(cfg), "--duration", "2"]) == 2
    err = capsys.readouterr().err
    assert "unstable closed loop" in err and "drive.loop_gain <" in err and not out.exists()
    cfg.write_text("[disturbance]\namplitude = nan\n")
    assert main(["simulate", "shaker-constant", "-o", str(out), "--config", str(cfg), "--duration", "2"]) == 2
    err = capsys.readouterr().err
    assert "force = nan N" in err and not out.exists()


def test_absurd_lengths_are_refused_or_bounded_not_allocated(tmp_path, capsys):
    # a hold of 1e9 s at 333 Hz once built 3e11 samples before keeping the trial's first n (MemoryError;
    # 1e6 s: 24 GB, killed), --duration 1e9 a 2.4 TiB array, loop_gain = 1e300 a ZeroDivisionError in
    # the refusal message; an accel or sine frequency of 0 a ZeroDivisionError
    base = simulate_scenario("shaker-constant", duration=3.0, seed=1)
    held = simulate_scenario("shaker-constant", duration=3.0, seed=1, config={"trajectory": {"hold": 1e9}})
    assert len(held.t) == len(base.t) == 999
    n_rest = int(round(0.2 * 333)) + int(round(0.02 / (1.0 / 333)))  # rest, then the ramp to 0.02 m/s
    np.testing.assert_array_equal(held.v_ref[:n_rest], base.v_ref[:n_rest])
    assert np.all(held.v_ref[n_rest + 1:] == 0.02)  # holding the first level to the end
    milling = simulate_scenario("milling-dec", duration=3.0, config={"trajectory": {"accel": 1e-9}})
    assert len(milling.t) == 999
    out = tmp_path / "never.mcap"
    for argv, says in ((["--duration", "1e9"], "more than one simulated trial holds (10,000,000"),
                       (["--config", "lg.toml"], "or an inertia > 1.5015e+297 kg"),
                       (["--config", "acc.toml"], "trajectory.accel must be a finite number > 0"),
                       (["--config", "freq.toml"], "trajectory.sine_frequencies must be a list of finite numbers > 0"),
                       (["--config", "amp.toml"], "trajectory.amplitudes must be a list of finite numbers within ±50 m/s"),
                       (["--config", "fine.toml", "--fine"], "fine=True: 999 samples × 30030 substeps")):
        (tmp_path / "lg.toml").write_text("[drive]\nloop_gain = 1e300\n")
        (tmp_path / "acc.toml").write_text("[trajectory]\naccel = 0.0\n")
        (tmp_path / "freq.toml").write_text("[trajectory]\nsine_frequencies = [0.0, 1.0, 2.0, 4.0, 8.0]\n")
        (tmp_path / "amp.toml").write_text("[trajectory]\namplitudes = [1e6]\n")
        (tmp_path / "fine.toml").write_text("fine_rate = 1e7\n")
        args = [a if not a.endswith(".toml") else str(tmp_path / a) for a in argv]
        assert main(["simulate", "shaker-constant", "-o", str(out), *(args if "--duration" in args else
                                                                     [*args, "--duration", "3"])]) == 2, argv
        err = capsys.readouterr().err
        assert says in err and "Traceback" not in err and not out.exists(), (argv, err)
