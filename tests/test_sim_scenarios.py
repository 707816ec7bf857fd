"""Scenarios of a drive in production: spindle-speed change, friction drift, payload step, force step.

Each trial is checked against what its constants say (truth columns, spindle columns, force
timing), against the PL-ARX model with the time-varying true β (exact path, noise-free), and
for byte-identity of the written file for the same seed.
"""

import math

import numpy as np
import pytest

from feedio.mcapio import read_trial
from feedmon.cli import main
from kernels.feed_drive import physical_to_beta, regressors
from replay import scenarios as SC
from replay.cutting import MillingTool, SpindleProfile, feed_force
from replay.simulator import simulate_scenario, write_trial

QUIET = {"noise": {"v_meas_std": 0.0, "glitch_rate": 0.0, "dynamometer_std": 0.0}}
#: a short spindle-change trial: 3000 rpm, 2400 rpm from 2 s, 3600 rpm from 4 s (default ramps, 5000 rpm/s)
SPINDLE = {"spindle": {"schedule": [[2.0, 2400.0], [4.0, 3600.0]]}}
NEW = ("milling-spindle-change", "shaker-drift", "milling-payload", "shaker-step")


def _quiet(**extra) -> dict:
    out = {k: dict(v) for k, v in QUIET.items()}
    out.update(extra)
    return out


def _roundtrip(res, tmp_path, name="t.mcap"):
    path = tmp_path / name
    write_trial(res, path)
    return read_trial(path)


def _tooth_line(force, t, Ts, t0, t1) -> float:
    """Frequency (Hz) of the largest line of the force spectrum between t0 and t1."""
    m = (t >= t0) & (t < t1)
    x = force[m] - force[m].mean()
    spec = np.abs(np.fft.rfft(x * np.hanning(x.size)))
    return float(np.fft.rfftfreq(x.size, Ts)[np.argmax(spec)])


# ---------------------------------------------------------------------------------------------
# milling-spindle-change
# ---------------------------------------------------------------------------------------------
def test_spindle_schedule_in_samples_and_force_spectrum(tmp_path):
    res = simulate_scenario("milling-spindle-change", duration=6.0, config=_quiet(**SPINDLE))
    tr = _roundtrip(res, tmp_path)
    t, rpm, angle = tr.t, tr.spindle_rpm, tr.spindle_angle
    assert rpm is not None and angle is not None and np.all(np.isfinite(angle))
    assert tr.meta.spindle_rpm is None  # no single speed: the samples carry it
    assert tr.meta.teeth == 2
    accel = SC.load_scenario("milling-spindle-change")["spindle"]["accel"]
    np.testing.assert_array_equal(rpm[t < 2.0], 3000.0)
    np.testing.assert_array_equal(rpm[(t >= 2.0 + 600.0 / accel) & (t < 4.0)], 2400.0)
    np.testing.assert_array_equal(rpm[t >= 4.0 + 1200.0 / accel], 3600.0)
    ramp = (t > 2.0) & (t < 2.0 + 600.0 / accel)
    assert ramp.any() and np.all((rpm[ramp] < 3000.0) & (rpm[ramp] > 2400.0)) and np.all(np.diff(rpm[ramp]) < 0)
    # the angle is the integral of the speed: each step advances by 2π/60 × the mean speed × Ts
    # (exact for the piecewise-linear speed except in the few samples where a ramp starts or ends)
    step = np.diff(angle)
    expect = 2 * np.pi / 60.0 * 0.5 * (rpm[1:] + rpm[:-1]) * tr.Ts
    assert np.sum(np.abs(step - expect) > 1e-9) <= 4
    np.testing.assert_allclose(step, expect, rtol=2e-3)
    assert angle[0] == pytest.approx(math.radians(SC.load_scenario("milling-spindle-change")["disturbance"]["phase"]))
    # tooth passing (2 teeth) follows the speed: 100 Hz, 80 Hz, 120 Hz
    force = tr.truth.force
    assert _tooth_line(force, t, tr.Ts, 0.7, 1.95) == pytest.approx(100.0, abs=0.8)
    assert _tooth_line(force, t, tr.Ts, 2.3, 3.95) == pytest.approx(80.0, abs=0.8)
    assert _tooth_line(force, t, tr.Ts, 4.4, 5.4) == pytest.approx(120.0, abs=0.9)


def test_force_follows_the_integrated_spindle_angle():
    """After an instantaneous change at t_s the force equals that of a constant-speed tool at the
    new speed whose angle at t_s is the integrated one (no jump; a θ = 2π n(t) t model fails)."""
    Ts = 1 / 333
    n = 1332
    feed = np.full(n, 0.006)
    t_s = 1.5 + 0.37 * Ts  # inside an interval
    sp = SpindleProfile(3000.0, [(t_s, 2400.0)], accel=0.0, phase=20.0)
    tool = MillingTool(phase=20.0)
    changed = feed_force(tool, 0.0, Ts, feed, spindle=sp)
    before = feed_force(tool, 0.0, Ts, feed)
    k_s = int(t_s / Ts)
    np.testing.assert_allclose(changed[:k_s], before[:k_s], rtol=0, atol=1e-9)
    theta_s = math.radians(20.0) + 2 * math.pi * 50.0 * t_s
    assert float(sp.angle(t_s)) == pytest.approx(theta_s, rel=1e-14)
    phase_new = math.degrees(theta_s - 2 * math.pi * 40.0 * t_s)  # same angle at t_s, 40 rev/s after
    # angle_step 0.4° at 2400 rpm: the same evaluation times as 0.5° at the profile's top speed
    after = feed_force(MillingTool(spindle_rpm=2400.0, phase=phase_new, angle_step=0.4), 0.0, Ts, feed)
    k1 = k_s + 1
    # same angles up to rounding; an evaluation point landing within rounding of a tooth's
    # entry/exit edge may switch one edge-force sub-point (≤ 0.7 N of ~100 N), so compare robustly
    err = np.abs(changed[k1:] - after[k1:])
    assert np.median(err) < 1e-6 and np.mean(err > 1e-6) < 0.01 and err.max() < 1.0
    wrong = feed_force(MillingTool(spindle_rpm=2400.0, phase=20.0), 0.0, Ts, feed)  # θ = 2π n t: jumps
    assert np.median(np.abs(changed[k1:] - wrong[k1:])) > 1.0
    # the chip load follows the speed: with the feed rate held, 2400 rpm cuts 25 % thicker chips
    assert changed[k1:].mean() > 1.05 * before[k1:].mean()


def test_feed_per_tooth_programme():
    """``feed = "per-tooth"`` (default): v_ref/(n N_t) equals the programmed feed per tooth at
    every speed; ``feed = "rate"``: the feed rate stays as programmed at the first speed."""
    cfg = _quiet(**SPINDLE)
    res = simulate_scenario("milling-spindle-change", duration=6.0, config=cfg)
    sc = SC.load_scenario("milling-spindle-change", cfg, duration=6.0)
    levels = np.array(sc["trajectory"]["levels"]) * 1e-3  # m per tooth
    c = res.v_ref / (res.spindle_rpm / 60.0 * 2)  # m per tooth
    steady = (res.t > 0.5) & (res.t < 5.5) & np.isclose(np.abs(np.gradient(res.v_ref)), 0.0, atol=1e-15)
    for lo, hi in ((0.6, 1.9), (2.3, 3.9), (4.4, 5.4)):
        m = steady & (res.t > lo) & (res.t < hi)
        assert m.sum() > 50
        dist = np.abs(c[m][:, None] - levels[None, :]).min(axis=1)
        assert dist.max() < 1e-12  # on a programmed level
    rate = simulate_scenario("milling-spindle-change", duration=6.0,
                             config=_quiet(spindle={"schedule": SPINDLE["spindle"]["schedule"], "feed": "rate"}))
    plain = simulate_scenario("milling-incdec", duration=6.0, config=_quiet())
    np.testing.assert_array_equal(rate.v_ref, plain.v_ref)
    assert not np.array_equal(res.v_ref, plain.v_ref)


def test_spindle_schedule_errors():
    with pytest.raises(ValueError, match=r"spindle.schedule\[1\].*inside the trial"):
        SC.load_scenario("milling-spindle-change", duration=20.0)
    with pytest.raises(ValueError, match=r"spindle.schedule\[0\].*speed"):
        SC.load_scenario("milling-spindle-change", {"spindle": {"schedule": [[1.0, -5.0]]}})
    with pytest.raises(ValueError, match=r"spindle.schedule\[1\].*after the previous"):
        SC.load_scenario("milling-spindle-change", {"spindle": {"schedule": [[3.0, 2000.0], [2.0, 2500.0]]}})
    with pytest.raises(ValueError, match="unknown scenario key 'spindle'"):
        SC.load_scenario("shaker-constant", {"spindle": {"schedule": []}})
    with pytest.raises(ValueError, match="spindle.feed"):
        SC.load_scenario("milling-spindle-change", {"spindle": {"feed": "mm/min"}})
    with pytest.raises(ValueError, match="turning spindle"):
        SC.load_scenario("milling-aircut", {"spindle": {"schedule": [[1.0, 2000.0]]}})


def test_spindle_profile_ramps():
    sp = SpindleProfile(3000.0, [(1.0, 2400.0), (1.05, 3000.0)], accel=5000.0)
    # the second command arrives mid-ramp (at 2750 rpm) and ramps back up from there
    assert float(sp.speed(1.05)) == pytest.approx(2750.0)
    assert float(sp.speed(1.10)) == pytest.approx(3000.0)
    assert float(sp.speed(0.5)) == 3000.0 and float(sp.speed(5.0)) == 3000.0
    t = np.linspace(0.0, 2.0, 200001)
    num = np.concatenate([[0.0], np.cumsum(0.5 * (sp.speed(t)[1:] + sp.speed(t)[:-1]) * np.diff(t))]) * 2 * np.pi / 60
    np.testing.assert_allclose(sp.angle(t), num, atol=1e-7)


# ---------------------------------------------------------------------------------------------
# drive constants over time
# ---------------------------------------------------------------------------------------------
def test_shaker_drift_truth_columns(tmp_path):
    res = simulate_scenario("shaker-drift", duration=6.0, config=_quiet())
    tr = _roundtrip(res, tmp_path)
    sc = SC.load_scenario("shaker-drift")
    d, drift = sc["drive"], sc["drive_drift"]
    assert drift["damping"] == drift["coulomb_pos"] == drift["coulomb_neg"] == 0.3 and drift["inertia"] == 0.0
    frac = tr.t / 6.0
    truth = tr.truth
    np.testing.assert_array_equal(truth.inertia, d["inertia"])
    np.testing.assert_allclose(truth.damping, d["damping"] * (1 + 0.3 * frac), rtol=1e-14)
    np.testing.assert_allclose(truth.coulomb_pos, d["coulomb_pos"] * (1 + 0.3 * frac), rtol=1e-14)
    np.testing.assert_allclose(truth.coulomb_neg, d["coulomb_neg"] * (1 + 0.3 * frac), rtol=1e-14)
    assert truth.damping[-1] == pytest.approx(1.3 * d["damping"], rel=1e-3)
    # the metadata keeps the values at t = 0 (= nominal), and says what varies
    phys = tr.meta.truth.physical
    assert phys["damping"] == d["damping"] and phys["coulomb_pos"] == d["coulomb_pos"]
    assert tr.meta.provenance.details["time_varying"] == ["damping", "coulomb_pos", "coulomb_neg"]
    np.testing.assert_array_equal(
        tr.meta.truth.beta,
        physical_to_beta("velocity-loop", tr.Ts, d["inertia"], d["damping"], gain=d["loop_gain"],
                         coulomb_pos=d["coulomb_pos"], coulomb_neg=d["coulomb_neg"]),
    )


def test_milling_payload_inertia_step(tmp_path):
    res = simulate_scenario("milling-payload", duration=5.0, config=_quiet())
    tr = _roundtrip(res, tmp_path)
    sc = SC.load_scenario("milling-payload")
    J0, at, rel = sc["drive"]["inertia"], sc["drive_step"]["at"], sc["drive_step"]["inertia"]
    assert rel > 0 and 0 < at < 1
    t_step = at * 5.0
    J = tr.truth.inertia
    np.testing.assert_array_equal(J[tr.t < t_step], J0)
    np.testing.assert_allclose(J[tr.t >= t_step], J0 * (1 + rel), rtol=1e-15)
    assert (tr.t < t_step).sum() == math.ceil(t_step / tr.Ts)
    np.testing.assert_array_equal(tr.truth.damping, sc["drive"]["damping"])
    np.testing.assert_array_equal(tr.truth.coulomb_pos, 0.0)
    assert tr.meta.truth.physical["inertia"] == J0 and tr.meta.spindle_rpm == 3000.0
    # the heavier table slows the closed loop: p_d − K_d rises after the step
    b = res.beta_series()
    assert (b[-1, 0] + b[-1, 1]) > (b[0, 0] + b[0, 1])


def test_shaker_step_force_timing():
    res = simulate_scenario("shaker-step", duration=4.0013, config=_quiet())
    sc = SC.load_scenario("shaker-step")
    F, start, stop = sc["disturbance"]["force"], sc["disturbance"]["start"], sc["disturbance"]["stop"]
    T = 4.0013
    Ts = res.meta.Ts
    on, off = start * T, stop * T
    k_on, k_off = int(on / Ts), int(off / Ts)
    force = res.force
    np.testing.assert_array_equal(force[:k_on], 0.0)
    np.testing.assert_array_equal(force[k_on + 1:k_off], F)
    np.testing.assert_array_equal(force[k_off + 1:], 0.0)
    # the intervals the edges cut hold the covered fraction (the force held over a sample is its mean)
    assert force[k_on] == pytest.approx(F * ((k_on + 1) * Ts - on) / Ts, rel=1e-9)
    assert force[k_off] == pytest.approx(F * (off - k_off * Ts) / Ts, rel=1e-9)
    np.testing.assert_array_equal(res.dynamometer, -force)  # no sensor noise in QUIET
    np.testing.assert_array_equal(res.inertia, sc["drive"]["inertia"])


@pytest.mark.parametrize(("name", "config"), [
    ("shaker-drift", {}),
    ("milling-payload", {}),
    ("shaker-step", {}),
    ("milling-spindle-change", SPINDLE),
])
def test_pl_arx_with_time_varying_truth(name, config, tmp_path):
    """Noise-free exact path: v_m(k+1) − β(k)ᵀz(k) equals the recorded f(k) = −b(k)·T_c(k),
    with β(k) from the recorded truth columns (constant β(0) does not fit a drifting drive)."""
    res = simulate_scenario(name, duration=6.0, config=_quiet(**config))
    tr = _roundtrip(res, tmp_path)
    truth, mt = tr.truth, tr.meta.truth
    K = tr.meta.loop_gain
    betas = np.array([
        physical_to_beta("velocity-loop", tr.Ts, J, B, gain=K, coulomb_pos=cp, coulomb_neg=cn, coulomb=mt.coulomb)
        for J, B, cp, cn in zip(truth.inertia, truth.damping, truth.coulomb_pos, truth.coulomb_neg)
    ])
    np.testing.assert_allclose(betas, res.beta_series(), rtol=1e-15, atol=0)
    reg = regressors("velocity-loop", tr.v_meas, v_ref=tr.v_ref, omega=mt.omega, coulomb=mt.coulomb)
    resid = reg.y - np.einsum("ij,ij->i", reg.Z, betas[:-1])
    scale = np.abs(truth.f).max()
    assert scale > 1e-5  # a disturbance acts
    np.testing.assert_allclose(resid, truth.f[:-1], rtol=0, atol=1e-10 * scale)
    b = (1 - np.exp(-truth.damping * tr.Ts / truth.inertia)) / truth.damping
    np.testing.assert_allclose(truth.f, -b * truth.force, rtol=1e-12, atol=0)
    varying = tr.meta.provenance.details.get("time_varying", [])
    if varying:
        const = reg.y - reg.Z @ betas[0]
        assert np.abs(const - truth.f[:-1]).max() > 100 * 1e-10 * scale


def test_fine_path_follows_the_time_varying_drive():
    """The 10 kHz path uses the same J(k), B(k): it stays close to the exact path after the step."""
    cfg = _quiet(drive_step={"inertia": 1.0})
    exact = simulate_scenario("milling-payload", duration=4.0, config=cfg)
    fine = simulate_scenario("milling-payload", duration=4.0, config=cfg, fine=True)
    np.testing.assert_array_equal(fine.inertia, exact.inertia)
    late = exact.t > 2.0
    err = np.abs(fine.v_true[late] - exact.v_true[late]).max()
    constant = simulate_scenario("milling-payload", duration=4.0, config=_quiet(), fine=True)
    effect = np.abs(constant.v_true[late] - fine.v_true[late]).max()  # what doubling the inertia does
    assert err < 0.01 * effect


def test_drive_variation_errors():
    with pytest.raises(ValueError, match=r"drive_step.inertia = -1.0 would make drive.inertia ≤ 0"):
        SC.load_scenario("milling-payload", {"drive_step": {"inertia": -1.0}})
    with pytest.raises(ValueError, match=r"drive_drift.coulomb_pos"):
        SC.load_scenario("shaker-drift", {"drive_drift": {"coulomb_pos": -1.5}})
    with pytest.raises(ValueError, match=r"drive_step.at"):
        SC.load_scenario("milling-payload", {"drive_step": {"at": 1.5}})
    with pytest.raises(ValueError, match=r"disturbance.start and .stop"):
        SC.load_scenario("shaker-step", {"disturbance": {"start": 0.8, "stop": 0.2}})
    with pytest.raises(ValueError, match=r"disturbance.force must be a finite number"):
        SC.load_scenario("shaker-step", {"disturbance": {"force": float("nan")}})


# ---------------------------------------------------------------------------------------------
# every scenario: truth columns, determinism, listing
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", SC.SCENARIOS)
def test_every_scenario_has_truth_columns(name, tmp_path):
    sc = SC.load_scenario(name)
    duration = None if "process" in sc else 6.0  # process scenarios: their events lie inside the whole part
    cfg = SPINDLE if name == "milling-spindle-change" else None
    tr = _roundtrip(simulate_scenario(name, duration=duration, config=cfg), tmp_path)
    for col in SC.VARYING:
        values = getattr(tr.truth, col)
        assert values is not None and values.shape == tr.t.shape and np.all(np.isfinite(values))
        assert values[0] == sc["drive"][col] == tr.meta.truth.physical[col]
        if name not in ("shaker-drift", "milling-payload"):
            np.testing.assert_array_equal(values, sc["drive"][col])
    milling = sc["disturbance"]["kind"] == "milling"
    assert (tr.spindle_angle is not None) == milling == (tr.spindle_rpm is not None)


@pytest.mark.parametrize("name", NEW)
def test_same_seed_same_bytes(name, tmp_path):
    cfg = SPINDLE if name == "milling-spindle-change" else None
    paths = []
    for i, seed in enumerate((3, 3, 4)):
        p = tmp_path / f"{i}.mcap"
        write_trial(simulate_scenario(name, seed=seed, duration=5.0, config=cfg, created="2026-01-02T03:04:05Z"), p)
        paths.append(p.read_bytes())
    assert paths[0] == paths[1]
    assert paths[0] != paths[2]


def test_cli_lists_scenarios(capsys):
    assert main(["simulate", "--list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == len(SC.SCENARIOS)
    for name, line in zip(SC.SCENARIOS, out):
        desc = SC.describe()[name]
        assert line.split()[0] == name and line.rstrip().endswith(desc) and len(desc) > 10
    assert main(["simulate"]) == 2
    assert "--list" in capsys.readouterr().err


def test_new_columns_are_checked_by_the_schema():
    from feedio import schema as S

    with pytest.raises(ValueError, match="field 'inertia' has 1 values but 't' has 2"):
        S.TruthBlock(seq=0, t=[0.0, 0.003], force=[0.0, 0.0], f=[0.0, 0.0], inertia=[300.0])
    with pytest.raises(S.SchemaError, match="spindle_angle"):
        S.decode_samples(b'{"machine":"m","axis":"X","seq":0,"t":[0.0],"v_ref":[0.0],"v_meas":[0.0],'
                         b'"spindle_angle":[1.0,2.0]}')
    with pytest.raises(S.SchemaError, match="coulomb_neg"):
        S.decode_truth(b'{"seq":0,"t":[0.0],"force":[0.0],"f":[0.0],"coulomb_neg":"x"}')
    ok = S.decode_truth(b'{"seq":0,"t":[0.0],"force":[0.0],"f":[0.0],"damping":[300.0]}')
    assert ok.damping == [300.0] and ok.inertia is None
