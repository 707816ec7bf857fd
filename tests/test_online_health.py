"""Issue 11 through the real path: ``feedmon simulate`` → ``feedmon identify`` (model files) →
``feedmon run --from`` → the MCAP output (estimates and the ``/<machine>/<axis>/health`` channel).

Checked: the spindle-phase kernel follows spindle-speed changes; without spindle data the change
raises a health warning within a second; online β follows drifting friction and an inertia step
(with warn/alarm); the real EMPS drive (a β1 20 % off, the pulses); health reports, their schema,
nulls and reasons; ``--config`` overrides; settings errors.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import msgspec
import numpy as np
import pytest
from trial_edit import rewrite_samples

from feedio import schema as S
from feedio.mcapio import OpenTrial, iter_blocks, read_trial
from feedmon.cli import main
from monitor.model_file import ModelFileError, load_model, save_model
from monitor.online_settings import SpindleKernel

TS = 1 / 333


def _identify(trial, out, *extra):
    assert main(["identify", str(trial), "-o", str(out), *map(str, extra)]) == 0
    return out


def _run(trial, model, out, config=None):
    argv = ["run", "--from", str(trial), "-o", str(out), "--model", str(model)]
    if config is not None:
        argv += ["--config", str(config)]
    assert main(argv) == 0
    return out


def _config(path, text):
    path.write_text(text)
    return path


def _estimates(path):
    """seq, t, force_next, flags of every row of the output."""
    blocks = [b for _, b in iter_blocks(path, kinds=("disturbance",))]
    seq = np.concatenate([np.arange(b.seq, b.seq + len(b.t)) for b in blocks])
    t = np.concatenate([np.asarray(b.t) for b in blocks])
    fn = np.concatenate([np.asarray(b.force_next, dtype=np.float64) for b in blocks])
    flags = np.concatenate([np.asarray(b.flags) for b in blocks])
    return seq, t, fn, flags


def _truth_at(trial, seq, name="force"):
    tr = read_trial(trial).truth
    pos = np.searchsorted(tr.seq, seq)
    assert np.array_equal(tr.seq[pos], seq)
    return getattr(tr, name)[pos]


def _health(path):
    return [b for _, b in iter_blocks(path, kinds=("health",))]


def _corr(a, b):
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def _strip_spindle(src, dst):
    """The same trial without the samples' spindle columns (a bridge without spindle data)."""
    return rewrite_samples(src, dst, lambda b: msgspec.structs.replace(b, spindle_rpm=None, spindle_angle=None))


# ---- milling: spindle-speed changes, payload ----------------------------------------------------------------
@pytest.fixture(scope="module")
def mill(tmp_path_factory, simulated):
    """A milling model identified (REML-tuned, what the model file then carries for the tracker) on a
    milling trial at constant 3000 rpm with spindle data in its samples."""
    d = tmp_path_factory.mktemp("mill")
    model = _identify(simulated("milling-incdec", seed=1, duration=20.0), d / "mill.model.toml", "--tune")
    return d, model


def test_a_trial_with_spindle_data_gets_the_spindle_phase_kernel(mill):
    _, model = mill
    m = load_model(model)
    k = m.tracker.kernel
    assert isinstance(k, SpindleKernel) and k.kind == "spindle" and k.per == "revolution" and k.teeth == 2
    assert k.spindle_rpm == pytest.approx(3000.0, rel=1e-6)
    assert m.tracker.forgetting == 0.998 and m.tracker.budget == 100
    ident = m.identification
    assert ident["tuned"] and k.sigma1 == pytest.approx(ident["sigma1"]) and m.tracker.gamma == pytest.approx(ident["gamma"])


@pytest.fixture(scope="module")
def spindle_change(mill, simulated):
    d, model = mill
    trial = simulated("milling-spindle-change", seed=2)
    return d, model, trial, _run(trial, model, d / "change.mcap")


def test_spindle_speed_changes_are_followed_with_spindle_data(spindle_change):
    """3000 → 2400 rpm at 14 s, → 3600 rpm at 27 s: force_next (the prediction of sample j made when it
    arrived) correlates with the true force ≥ 0.97 over the trial and ≥ 0.95 in the second after each change."""
    _, _, trial, out = spindle_change
    seq, t, fn, flags = _estimates(out)
    force = _truth_at(trial, seq)
    use = (flags & int(S.WARMUP)) == 0
    assert _corr(fn[use], force[use]) >= 0.97
    for change in (14.0, 27.0):
        w = use & (t >= change) & (t < change + 1.0)
        assert w.sum() > 300 and _corr(fn[w], force[w]) >= 0.95, change
    states = [h.state for h in _health(out)]
    assert states.count("ok") == len(states)          # the model explains the data all along


def test_health_reports_about_once_a_second_with_values_and_schema(spindle_change):
    _, _, trial, out = spindle_change
    reports = _health(out)
    duration = read_trial(trial).t[-1]
    assert abs(len(reports) - duration) <= 2
    t = np.array([h.t for h in reports])
    assert np.all(np.diff(t) > 0.9) and np.all(np.diff(t) < 1.1)
    h = reports[-1]
    assert h.machine == "cnc-mill" and h.axis == "X" and h.adaptation == "track"
    assert h.inertia == pytest.approx(_truth_at(trial, np.array([h.seq]), "inertia")[0], rel=0.05)
    assert h.inertia_se > 0 and h.coulomb is None  # no Coulomb columns in this model (no speed reversal)
    assert h.offset is not None and h.offset_se > 0  # the intercept column "one" (model file version 2)
    assert any("coulomb" in r and "no such column" in r for r in h.reasons)
    assert any(r.startswith("not determined by the data") and "damping" in r for r in h.reasons)
    with OpenTrial(out) as f:                               # a JSON Schema on the channel, written as null
        ch = f.channels["/cnc-mill/X/health"]
        schema = json.loads(f.file.schemas[ch.schema_id].data)
    assert schema["title"] == "Health" and "coulomb" in schema["properties"]
    raw = S.encode(h)
    assert b'"coulomb":null' in raw and S.decode_health(raw) == h


def test_without_spindle_data_the_change_raises_a_warning_within_two_seconds(mill, simulated, tmp_path, caplog):
    """Warn 1.5 s after the change (0.44 s before the variances were calibrated online: the calibration takes
    up part of the rise of ν² while the disturbance search looks for the new period)."""
    d, model = mill
    trial = _strip_spindle(simulated("milling-spindle-change", seed=2), tmp_path / "nospindle.mcap")
    with caplog.at_level(logging.WARNING):
        out = _run(trial, model, tmp_path / "est.mcap")
    assert "without usable spindle data" in caplog.text   # said clearly, and counted
    reports = _health(out)
    before = [h for h in reports if h.t < 14.0]
    assert before and all(h.state == "ok" for h in before)
    first = next(h for h in reports if h.state != "ok")
    assert 14.0 < first.t <= 16.0, first
    assert first.reasons[0].startswith("innovation: the model does not explain the data")
    assert "health ok → " in caplog.text                   # the log says the change of state once


def test_inertia_step_raises_warn_and_is_followed(mill, simulated, tmp_path):
    """+20 % inertia at 24 s of 60 s: warn/alarm within 5 s, online inertia within 3 % of the new value
    within 30 s (and it stays there)."""
    _, model = mill
    trial = simulated("milling-payload", seed=4)
    out = _run(trial, model, tmp_path / "payload.mcap")
    reports = _health(out)
    step = 24.0
    assert all(h.state == "ok" for h in reports if h.t < step)
    first = next(h for h in reports if h.t >= step and h.state != "ok")
    assert first.t - step <= 5.0 and any(r.startswith(("inertia drift +", "inertia step +")) for r in first.reasons)
    J_new = _truth_at(trial, np.array([reports[-1].seq]), "inertia")[0]
    err = np.array([abs(h.inertia / J_new - 1) for h in reports if h.t >= step])
    t_after = np.array([h.t for h in reports if h.t >= step])
    within = np.flatnonzero(err <= 0.03)
    settled = next(i for i in within if np.all(err[i:] <= 0.03))
    assert t_after[settled] - step <= 30.0


# ---- shaker with drifting friction ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def shaker(tmp_path_factory, simulated):
    d = tmp_path_factory.mktemp("shaker")
    model = _identify(simulated("shaker-constant", seed=1, duration=20.0), d / "shaker.model.toml",
                      "--period", 1 / 55)
    return d, model


def test_drifting_friction_is_followed_within_5_percent(shaker, simulated):
    """Viscous and Coulomb friction +30 % over 120 s: online inertia, damping and Coulomb (the mean of
    both directions) within 5 % of the truth channel's values from 60 s on (default settings)."""
    d, model = shaker
    trial = simulated("shaker-drift", seed=3)
    out = _run(trial, model, d / "drift.mcap")
    late = [h for h in _health(out) if h.t >= 60.0]
    seq = np.array([h.seq for h in late])
    truth = {k: _truth_at(trial, seq, k) for k in ("inertia", "damping", "coulomb_pos", "coulomb_neg")}
    truth["coulomb"] = 0.5 * (truth["coulomb_pos"] + truth["coulomb_neg"])
    # measured (seeds 3, 4, 7): inertia 0.1 %, damping 3.3–3.4 %, Coulomb 3.8–4.2 % with the default memories
    # (friction 5 s, inertia 10 s; kernels/beta_tracker.py "Drift rate trade-off"); a fixed β ends 13 % off
    for name, bound in (("inertia", 0.05), ("damping", 0.05), ("coulomb", 0.05)):
        got = np.array([getattr(h, name) for h in late])
        assert np.max(np.abs(got / truth[name] - 1)) <= bound, (name, np.max(np.abs(got / truth[name] - 1)))
    # the reports follow the drift (truth +13 % of damping from 60 s to the end, a fixed β 0 %); whether it
    # is flagged depends on the drift test's thresholds (6 standard errors: no false alarm in 24 h)
    assert late[-1].damping / late[0].damping > 1.0 + 0.7 * (truth["damping"][-1] / truth["damping"][0] - 1)


def test_a_symmetric_coulomb_drop_is_drift_tested(simulated, tmp_path):
    """Out of sample, no flags: a model from the shaker's control run (no disturbance), then a shaker trial
    whose Coulomb friction drops 36 % in both directions half-way (the shaker on from 15 s to 45 s). The
    symmetric Coulomb level, the one a trial with reversals determines, is tested for drift: a report
    after the drop names it, with its sign; none before the drop does."""
    model = _identify(simulated("shaker-control", seed=1), tmp_path / "control.model.toml")
    step = _config(tmp_path / "step.toml", "duration = 60.0\n[drive_step]\nat = 0.5\n"
                   "coulomb_pos = -0.36\ncoulomb_neg = -0.36\n")
    trial = tmp_path / "step.mcap"
    assert main(["simulate", "shaker-constant", "-o", str(trial), "--seed", "2", "--config", str(step)]) == 0
    reports = _health(_run(trial, model, tmp_path / "step-out.mcap"))
    drift = [h for h in reports if any(r.startswith("coulomb drift") for r in h.reasons)]
    assert drift, [h.reasons for h in reports[-3:]]
    assert min(h.t for h in drift) > 30.0                  # nothing before the drop
    assert all(h.state != "ok" for h in drift)
    assert all("coulomb drift −" in r for h in drift for r in h.reasons if r.startswith("coulomb drift"))
    assert drift[-1].coulomb < 0.8 * reports[0].coulomb    # the estimate followed the drop


def test_applied_beta_keeps_the_disturbance_at_least_as_good_as_a_fixed_beta(shaker, simulated):
    d, model = shaker
    trial = simulated("shaker-drift", seed=3)
    corr = {}
    for mode in ("off", "apply"):
        cfg = _config(d / f"{mode}.toml", f'[run.adaptation]\nmode = "{mode}"\n')
        out = _run(trial, model, d / f"drift-{mode}.mcap", config=cfg)
        seq, _, fn, flags = _estimates(out)
        use = (flags & int(S.WARMUP)) == 0
        corr[mode] = _corr(fn[use], _truth_at(trial, seq)[use])
        if mode == "off":
            h = _health(out)[-1]
            assert h.adaptation == "off" and h.inertia is None and h.damping is None
            assert any("adaptation off" in r for r in h.reasons)
    assert corr["apply"] >= corr["off"] and corr["apply"] > 0.95


def test_the_coulomb_split_is_not_learned_in_motion(simulated, tmp_path):
    """Moving samples tell the symmetric Coulomb friction, not its split into asymmetry and offset
    (z_sp + z_sn + z_one = 0 for every z in motion). The tracker learns the samples at rest too, and its
    prediction of z carried them into β's regressors: with the model identified on a 250 Hz shaker trial
    (tests/data/models) a run over another seed warned 'coulomb_pos +51 %, coulomb_neg −41 %, offset −48 %'
    at 6–8 standard errors in its first 8 s, and the self-check said alarm. β now learns off that direction:
    nothing is flagged, the split keeps the file's values ("not determined" online), the symmetric
    friction is learned."""
    cfg = _config(tmp_path / "250.toml", "rate = 250.0\nblock = 50\n")
    trial = tmp_path / "shaker-250.mcap"
    assert main(["simulate", "shaker-constant", "-o", str(trial), "--seed", "2", "--duration", "30",
                 "--config", str(cfg)]) == 0
    model = Path(__file__).parent / "data" / "models" / "shaker-250hz.model.toml"
    reports = _health(_run(trial, model, tmp_path / "est.mcap"))
    assert len(reports) >= 25
    assert [(h.t, h.reasons) for h in reports if h.state != "ok"] == []
    late = reports[-1]
    assert any(r.startswith("not determined") and "coulomb_pos" in r and "offset" in r for r in late.reasons)
    truth = 0.5 * (_truth_at(trial, [late.seq], "coulomb_pos")[0] + _truth_at(trial, [late.seq], "coulomb_neg")[0])
    # (its standard error is the Huber–White sandwich's: it counts the innovations the model did not expect)
    assert late.coulomb == pytest.approx(truth, rel=0.05) and late.coulomb_se < 0.1 * truth


# ---- the real EMPS drive ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def emps(tmp_path_factory, emps_file):
    d = tmp_path_factory.mktemp("emps_online")
    for name, mat in (("plain", "DATA_EMPS.mat"), ("pulses", "DATA_EMPS_PULSES.mat")):
        assert main(["import", "emps", str(emps_file(mat)), "-o", str(d / f"{name}.mcap")]) == 0
    model = _identify(d / "plain.mcap", d / "emps.model.toml", "--period", 1.0, "--tune")
    return d, model


def test_emps_inertia_is_recovered_from_a_model_with_beta1_20_percent_off(emps, capsys):
    """β1 (the force gain 1/… of the model file) +20 %: the online mass M is within 3 % of the offline
    value from 10 s of motion on. (Fv and the Coulomb forces are not: see docs/online-health.md, Limits; printed here.)"""
    d, model = emps
    m = load_model(model)
    offline = dict(m.physical)
    m.beta[0] *= 1.2
    bad = save_model(m, d / "emps-bad.model.toml")
    out = _run(d / "plain.mcap", bad, d / "emps-bad.mcap")
    tr = read_trial(d / "plain.mcap")
    motion = np.cumsum(np.abs(tr.v_meas) > m.omega) * tr.Ts
    reports = _health(out)
    t_motion = motion[np.searchsorted(tr.seq, [h.seq for h in reports])]
    late = [h for h, tm in zip(reports, t_motion) if tm >= 10.0]
    assert len(late) >= 10
    eM = max(abs(h.inertia / offline["inertia"] - 1) for h in late)
    eFv = max(abs(h.damping / offline["damping"] - 1) for h in late)
    assert eM <= 0.03
    # the file's inertia is 20 % off and says so; nothing else is reported as a drift (the Coulomb
    # forces, learnt only from what the tracker cannot predict, are "not determined" on this drive)
    assert late[-1].state == "alarm" and any(r.startswith("inertia drift") for r in late[-1].reasons)
    drifts = {r.split(" ")[0] for h in reports for r in h.reasons if " drift " in r}
    assert drifts == {"inertia"}, drifts
    with capsys.disabled():
        print(f"\n  EMPS β1 +20 %: max |M error| {100 * eM:.2f} %, max |Fv error| {100 * eFv:.1f} % "
              f"(from 10 s of motion; Fv ± {late[-1].damping_se:.0f} N·s/m)")


def test_emps_online_friction_agrees_with_least_squares_above_min_speed(emps):
    """The real drive's friction is ~6 N below the Coulomb + viscous law under ~3.5 cm/s (identify's
    low-speed check writes min_speed). Learning from those samples — where the tracker's innovations
    are largest, at every reversal and start — read the departure as friction: with its own model the
    online damping came out +25 %, the Coulomb friction −11 %. Above min_speed: −8 % ± 20 % (the GP
    view determines the damping weakly here) and +0.8 %."""
    d, model = emps
    m = load_model(model)
    assert 0.01 < m.online.adaptation.min_speed < 0.1                        # m/s
    reports = _health(_run(d / "plain.mcap", model, d / "own-friction.mcap"))
    late = reports[len(reports) // 2:]
    fv = np.mean([h.damping for h in late])
    fc = np.mean([h.coulomb for h in late])
    assert abs(fc / m.physical["coulomb"] - 1) < 0.05, fc
    assert abs(fv / m.physical["damping"] - 1) < 0.15, fv


def test_emps_pulses_force_next_at_the_documented_alignment(emps):
    d, model = emps
    out = _run(d / "pulses.mcap", model, d / "pulses-est.mcap")
    seq, _, fn, _ = _estimates(out)
    force = _truth_at(d / "pulses.mcap", seq)
    ok = np.isfinite(fn)
    rms = float(np.sqrt(np.mean((fn[ok] - force[ok]) ** 2)))
    assert rms <= 15.0 and _corr(fn, force) >= 0.99, (rms, _corr(fn, force))


@pytest.mark.parametrize("trial", ["plain", "pulses"])
def test_emps_with_its_own_model_raises_no_health_warning(emps, trial):
    """The real drive with the model identified on it: every report ``ok`` (no false drift alarm). The
    Coulomb step at the end of the dead band and at reversals is not the real drive's force there
    (stiction, presliding); learning from those samples once gave "Coulomb −80 %" at 15–20 standard
    errors."""
    d, model = emps
    out = _run(d / f"{trial}.mcap", model, d / f"{trial}-health.mcap")
    reports = _health(out)
    assert len(reports) >= 20
    assert [(h.t, h.reasons) for h in reports if h.state != "ok"] == []


# ---- settings: model file tables, --config overrides, errors --------------------------------------------------
def test_settings_live_in_the_model_file_and_errors_name_the_key(shaker, tmp_path):
    _, model = shaker
    text = model.read_text()
    assert "[adaptation]" in text and 'mode = "track"' in text and "[health]" in text
    bad = tmp_path / "bad.model.toml"
    assert "\nmemory = 5.0" in text and "\ninertia_memory = 10.0" in text
    for key in ("memory", "inertia_memory"):
        bad.write_text(text.replace(f"\n{key} = ", f"\n{key} = 0.01 #"))
        with pytest.raises(ModelFileError, match=rf"adaptation\.{key}.*≥ 0\.5, ≤ 3600") as err:
            load_model(bad)
        assert str(bad) in str(err.value)
    bad.write_text(text.replace('mode = "track"', 'mode = "learn"'))
    with pytest.raises(ModelFileError, match="adaptation.mode.*'apply' / 'off' / 'track'"):
        load_model(bad)
    bad.write_text(text.replace("warn = 5.0", "warn = 9.0"))
    with pytest.raises(ModelFileError, match="clear < warn < alarm"):
        load_model(bad)


def test_config_overrides_reach_every_axis_and_are_checked(shaker, simulated, tmp_path, capsys):
    d, model = shaker
    trial = simulated("shaker-constant", seed=1, duration=20.0)
    cfg = _config(tmp_path / "c.toml", "[run.tracker]\nforgetting = 0.996\n[run.health]\nperiod = 2.0\n")
    out = _run(trial, model, tmp_path / "o.mcap", config=cfg)
    t = np.array([h.t for h in _health(out)])
    assert 8 <= t.size <= 11 and np.all(np.diff(t) >= 1.9)
    bad = _config(tmp_path / "bad.toml", "[run.adaptation]\nhuber = 0.1\n")
    assert main(["run", "--from", str(trial), "-o", str(tmp_path / "x.mcap"), "--model", str(model),
                 "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "run.adaptation.huber" in err and "1 ≤ huber ≤ 100" in err
    bad = _config(tmp_path / "bad2.toml", "[run.health]\nalarm = 4.0\n")
    assert main(["run", "--from", str(trial), "-o", str(tmp_path / "y.mcap"), "--model", str(model),
                 "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "clear < warn < alarm" in err and "the health overrides for " in err
    assert err.rstrip().endswith("(command line: --config)")
