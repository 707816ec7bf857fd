"""`feedmon identify`: candidates chosen by evidence among the valid ones, on simulated trials with known
truth and on the real EMPS drive (issue 10). Every identification runs once per session (cached)."""

import contextlib
import io
import json
import math

import numpy as np
import pytest
from trial_edit import rewrite_samples

from feedio.mcapio import TrialTooLong, iter_blocks, read_trial
from feedmon.cli import main
from kernels.errors import ParameterError
from monitor.identify import identify
from monitor.model_file import load_model
from replay.importers import EMPS_REFERENCE
from replay.scenarios import load_scenario
from replay.simulator import simulate, write_trial

SHAKER_PERIOD = 1 / 55
JSON_KEYS = {"form", "Ts", "chosen", "period", "candidates", "ls", "pl_lssvm", "model", "truth", "checks", "self_check",
             "error"}
PHYSICAL_KEYS = {"inertia", "damping", "coulomb", "coulomb_pos", "coulomb_neg", "offset"}

_RUNS: dict = {}


def run_identify(trial, *args, output=None) -> tuple[int, dict | None, str]:
    """``feedmon identify TRIAL ARGS --json [-o output | --dry-run]`` → (exit code, JSON document, stderr); cached."""
    key = (str(trial), args, str(output))
    if key not in _RUNS:
        argv = ["identify", str(trial), *map(str, args), "--json"] + (["-o", str(output)] if output else ["--dry-run"])
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(argv)
        text = out.getvalue()
        _RUNS[key] = (code, json.loads(text) if text.strip() else None, err.getvalue())
    return _RUNS[key]


def _rel(est, true):
    est, true = np.asarray(est[:2]), np.asarray(true[:2])
    return np.abs(est - true) / np.abs(true)


def _emps_errors(phys):
    fc = (phys["coulomb_pos"] + phys["coulomb_neg"]) / 2  # published Fc is symmetric
    assert fc == pytest.approx(phys["coulomb"], rel=1e-12)
    return (phys["inertia"] / EMPS_REFERENCE["M"] - 1, phys["damping"] / EMPS_REFERENCE["Fv"] - 1,
            fc / EMPS_REFERENCE["Fc"] - 1, phys["offset"] - EMPS_REFERENCE["offset"])


@pytest.fixture(scope="module")
def emps_trials(tmp_path_factory, emps_file):
    out = {}
    folder = tmp_path_factory.mktemp("emps")
    for name, mat, rate in (("plain", "DATA_EMPS.mat", 333), ("plain1000", "DATA_EMPS.mat", 1000),
                            ("pulses", "DATA_EMPS_PULSES.mat", 333)):
        out[name] = folder / f"{name}.mcap"
        assert main(["import", "emps", str(emps_file(mat)), "-o", str(out[name]), "--rate", str(rate)]) == 0
    return out


# ------------------------------------------------------------------------------------------------
# the real drive
# ------------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("trial", ["plain", "plain1000"])
def test_emps_clean_data_chooses_ls_and_writes_the_published_model(emps_trials, tmp_path_factory, trial):
    """No disturbance: a kernel in time would take the Coulomb friction (it competes with sign(v));
    the choice must not fall for it — the model written is as good as LS."""
    model_path = tmp_path_factory.mktemp("m") / "emps.model.toml"
    code, doc, _ = run_identify(emps_trials[trial], output=model_path)
    assert code == 0 and set(doc) == JSON_KEYS
    assert doc["chosen"] == "ls" and doc["model"]["method"] == "ls"
    model = load_model(model_path)
    m, fv, fc, offset = _emps_errors(model.physical)
    assert abs(m) < 0.01 and abs(fv) < 0.03 and abs(fc) < 0.03 and abs(offset) < 1.0, (m, fv, fc, offset)
    assert model.beta_names[-1] == "one" and model.beta_se is not None
    assert set(model.physical) == PHYSICAL_KEYS and set(model.physical_se) == PHYSICAL_KEYS
    kernels = [c for c in doc["candidates"] if c["method"] == "pl_lssvm"]
    assert kernels and all(not c["valid"] for c in kernels)
    best = max(kernels, key=lambda c: c["log_evidence"])  # the kernel "explains" more, yet is no valid choice
    assert best["log_evidence"] > doc["candidates"][0]["log_evidence"] and "competes" in best["why_not"]
    assert any("no rest" in n for n in doc["ls"]["notes"])  # asymmetry and offset not separable: said so
    # the friction near standstill departs from the law (~6 N below it under ~3.5 cm/s, at 333 Hz and 1 kHz
    # alike): found, said, and the online β learns only above it (kernels/low_speed.py)
    assert 0.02 < model.online.adaptation.min_speed < 0.05
    assert any("does not hold near standstill" in n for n in doc["ls"]["notes"])
    # the self-check (monitor.self_check) is what `feedmon run --from` with this file says of this trial, and
    # the file carries its verdict. It was "alarm, damping +21 %" while β learned from the low-speed samples
    check = doc["self_check"]
    out = model_path.with_suffix(".mcap")
    assert main(["run", "--from", str(emps_trials[trial]), "-o", str(out), "--model", str(model_path)]) == 0
    reports = [b for _, b in iter_blocks(out, kinds=("health",))]
    assert check["reports"] == len(reports) >= 20
    assert check["flagged"] == sum(h.state != "ok" for h in reports)
    assert check["state"] == max((h.state for h in reports), key=("ok", "warn", "alarm").index)
    assert model.identification["self_check"] == check["summary"]
    assert check["state"] == "ok", check["summary"]


@pytest.mark.slow
def test_emps_pulses_period_found_and_disturbance_recovered(emps_trials):
    code, doc, _ = run_identify(emps_trials["pulses"])
    assert code == 0
    assert doc["period"]["source"] == "detected" and doc["period"]["value"] == pytest.approx(1.0, rel=0.02)
    assert doc["chosen"] == "pl_lssvm"
    m, fv, fc, _ = _emps_errors(doc["model"]["physical"])
    # with the pulse force known, least squares on this trial gives Fv = 214 N·s/m (+5.3 %): the data's own
    # answer; the test allows that (see the report)
    assert abs(m) < 0.02 and abs(fv) < 0.06 and abs(fc) < 0.05, (m, fv, fc)
    m_ls, _, _, _ = _emps_errors(doc["ls"]["physical"])
    assert abs(m_ls) > 1.0  # LS: the unknown 176 N pulses bias M by hundreds of percent
    assert doc["truth"]["disturbance_correlation"] >= 0.99
    # the offset holds the pulses' mean force (88 N): said so, never passed off as the drive's offset
    offset_told = ("offset" in doc["pl_lssvm"]["undetermined"]
                   or any("mean force" in n for n in doc["pl_lssvm"]["notes"]))
    assert offset_told, doc["pl_lssvm"]["notes"]
    # the monitor with this model (its tracker: the zero-mean periodic kernel) over the same trial moves the
    # inertia −33 % from the first, unforeseen 178 N pulse edge on and ends near 56 kg (batch: 94 kg), whatever
    # its budget, λ or instrument: the recursive and the batch estimate disagree on these data with this kernel
    # and the identification tells the user before the file is used
    check = doc["self_check"]
    assert check["state"] in ("warn", "alarm") and any(r.startswith("inertia drift") for r in check["reasons"])


@pytest.mark.slow
@pytest.mark.parametrize("period", [0.8, 2.0])
def test_emps_pulses_wrong_period_is_noticed(emps_trials, tmp_path_factory, period):
    model_path = tmp_path_factory.mktemp("m") / "wrong.model.toml"
    code, doc, _ = run_identify(emps_trials["pulses"], "--period", period, output=model_path)
    assert code == 0 and doc["period"]["value"] == period and doc["period"]["source"] == "given"
    assert doc["period"]["suggested"] == pytest.approx(1.0, rel=0.02)
    assert any("the data prefer ψ = 1" in n for n in doc["ls"]["notes"])
    load_model(model_path)  # what was written is a model that can be right


@pytest.mark.slow
@pytest.mark.parametrize("trial, period", [("plain", 1.0), ("pulses", 0.5)])
def test_no_period_makes_identify_write_an_invalid_model(emps_trials, tmp_path_factory, trial, period):
    model_path = tmp_path_factory.mktemp("m") / "p.model.toml"
    code, doc, err = run_identify(emps_trials[trial], "--period", period, output=model_path)
    if code == 0:
        model = load_model(model_path)  # refuses a model that cannot be right
        assert model.validity_problems() == []
        chosen = [c for c in doc["candidates"] if c["valid"]]
        assert chosen and doc["chosen"] in {c["method"] for c in chosen}
    else:
        assert code == 1 and not model_path.exists() and "not" in err


# ------------------------------------------------------------------------------------------------
# simulated drives with known truth
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("scenario", ["shaker-constant", "shaker-sweep"])
def test_shaker_pl_lssvm_unbiased_ls_biased(simulated, scenario):
    code, doc, _ = run_identify(simulated(scenario, duration=20.0), "--period", SHAKER_PERIOD)
    assert code == 0 and doc["chosen"] == "pl_lssvm"
    truth = doc["truth"]["beta"]
    pl_err = _rel(doc["pl_lssvm"]["beta"], truth)
    ls_err = _rel(doc["ls"]["beta"], truth)
    assert np.all(pl_err < 0.005), pl_err
    assert ls_err.max() >= 5 * pl_err.max(), (ls_err, pl_err)
    assert doc["truth"]["disturbance_correlation"] > 0.95
    assert doc["pl_lssvm"]["beta_names"] == ["v_ref", "v_meas", "-sigma_p", "-sigma_n", "one"]
    errs = doc["truth"]["model_physical_error"]
    assert errs["inertia"] < 0.01 and errs["damping"] < 0.02 and errs["coulomb"] < 0.05


def test_milling_incdec_period_from_spindle_and_the_cutting_force_kept_out_of_damping_and_offset(simulated):
    code, doc, _ = run_identify(simulated("milling-incdec", duration=20.0))
    assert code == 0
    assert doc["period"] == {"value": pytest.approx(0.02), "source": "spindle", "suggested": None}
    assert any("no speed reversal" in n for n in doc["ls"]["notes"])  # Coulomb columns dropped, and said so
    assert doc["pl_lssvm"]["beta_names"] == ["v_ref", "v_meas", "one"]
    truth = doc["truth"]["beta"]
    assert np.all(_rel(doc["pl_lssvm"]["beta"], truth) < 0.02)
    assert _rel(doc["ls"]["beta"], truth)[0] > 0.2  # LS badly biased by the cutting force
    # the mean cutting force (~23 N + 1950 N·s/m × feed) once went into offset (+22 N) and damping (2213 for
    # 375 N·s/m): the cut is found in the residual and its mean kept apart (nuisance columns, the disturbance
    # model gated to it); damping and offset come from the half second of motion before the cut — honestly
    # imprecise there ("undetermined"), but right
    checks = doc["checks"]
    assert checks["offset_separated"] is True and checks["process"]["nuisance"] == ["process", "process*v_meas"]
    assert 0.9 < checks["process"]["share"] < 0.99
    phys, se = doc["model"]["physical"], doc["model"]["physical_se"]
    assert abs(phys["offset"]) < max(3 * se["offset"], 1.0)
    assert abs(phys["damping"] - 375.0) < 3 * se["damping"] and "damping" in doc["pl_lssvm"]["undetermined"]


@pytest.fixture(scope="module")
def far_trials(tmp_path_factory):
    """Drives far from the defaults: J, B × 0.2 and × 5, and the ratio B/J changed 25× either way; the loop
    gain keeps K_d of the default drive (closed-loop pole p_d − K_d unchanged in stability)."""
    folder = tmp_path_factory.mktemp("far")
    out = {}
    for scenario in ("shaker-control", "shaker-constant"):
        base = load_scenario(scenario)
        d, Ts = base["drive"], 1.0 / base["rate"]
        kd = d["loop_gain"] * (1 - math.exp(-d["damping"] * Ts / d["inertia"])) / d["damping"]
        for fj, fb in ((0.2, 0.2), (5.0, 5.0), (5.0, 0.2), (0.2, 5.0)):
            J, B = d["inertia"] * fj, d["damping"] * fb
            K = kd * B / (1 - math.exp(-B * Ts / J))
            sc = load_scenario(scenario, {"drive": {"inertia": J, "damping": B, "loop_gain": K}}, duration=20.0)
            path = folder / f"{scenario}-{fj}-{fb}.mcap"
            write_trial(simulate(sc, seed=3), path)
            out[(scenario, fj, fb)] = path
    return out


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["shaker-control", "shaker-constant"])
@pytest.mark.parametrize("fj, fb", [(0.2, 0.2), (5.0, 5.0), (5.0, 0.2), (0.2, 5.0)])
def test_drives_far_from_the_defaults(far_trials, scenario, fj, fb):
    code, doc, _ = run_identify(far_trials[(scenario, fj, fb)])
    assert code == 0
    truth = doc["truth"]["physical"]
    phys = doc["model"]["physical"]
    assert phys["inertia"] == pytest.approx(truth["inertia"], rel=0.02)
    assert phys["damping"] == pytest.approx(truth["damping"], rel=0.02)
    for key in ("coulomb_pos", "coulomb_neg"):  # right sign and direction (+ 9 N, − 10 N in the scenario)
        assert phys[key] == pytest.approx(truth[key], rel=0.05)
    assert doc["chosen"] == ("ls" if scenario == "shaker-control" else "pl_lssvm")


def test_spindle_speed_changes_are_identified_with_the_spindle_phase_kernel(simulated, tmp_path):
    """A milling trial whose spindle goes 3000 → 2400 → 3600 rpm (the cutting force follows the spindle):
    time kernels at one period each explain a part of the record and leave the inertia at about half its
    value (LS: 852 kg for 1500 on these 30 s). The spindle-phase candidate — the tracker's kernel on (t, θ) — explains all
    of it: it is chosen, finds the inertia, and the monitor with the written model agrees (self-check ok)."""
    model_path = tmp_path / "sc.model.toml"
    code, doc, _ = run_identify(simulated("milling-spindle-change", seed=11, duration=30.0), output=model_path)
    assert code == 0
    spindle = {c["hyperparameters"]["per"]: c for c in doc["candidates"] if c["kernel"] == "spindle"}
    assert set(spindle) == {"revolution", "tooth"} and all(c["valid"] for c in spindle.values())
    best = max(spindle.values(), key=lambda c: c["log_evidence"])
    assert best["hyperparameters"]["per"] == "revolution"  # the simulated tool has runout (a spindle-frequency line)
    best_time = max(c["log_evidence"] for c in doc["candidates"] if c["kernel"] not in (None, "spindle"))
    assert best["log_evidence"] > best_time + 1000
    assert doc["chosen"] == "pl_lssvm" and doc["pl_lssvm"]["kernel"] == "spindle"
    truth = doc["truth"]["physical"]["inertia"]
    J, sJ = doc["model"]["physical"]["inertia"], doc["model"]["physical_se"]["inertia"]
    assert J == pytest.approx(truth, rel=0.02) and abs(J - truth) < 4 * sJ + 0.005 * truth
    assert sJ < doc["ls"]["physical_se"]["inertia"]     # better determined than by least squares
    assert abs(doc["ls"]["physical"]["inertia"] / truth - 1) > 0.3  # (what LS makes of the same data)
    check = doc["self_check"]
    assert check["state"] == "ok", check["summary"]
    assert check["online"]["inertia"]["value"] == pytest.approx(truth, rel=0.03)
    model = load_model(model_path)                     # the tracker runs the kernel identification tuned
    assert model.tracker.kernel.kind == "spindle" and model.tracker.kernel.per == "revolution"
    assert model.tracker.kernel.sigma1 == pytest.approx(best["hyperparameters"]["sigma1"])
    assert model.tracker.gamma == pytest.approx(best["hyperparameters"]["gamma"])
    assert sorted(c["per"] for c in model.candidates if c["kernel"] == "spindle") == ["revolution", "tooth"]


def _with_spindle_column(src, dst, rpm_at):
    """``src`` with a ``spindle_rpm`` column ``rpm_at(t)`` added to every sample block (truth kept)."""
    import msgspec

    return rewrite_samples(src, dst, lambda b: msgspec.structs.replace(b, spindle_rpm=rpm_at(np.asarray(b.t)).tolist()))


def test_a_disturbance_that_does_not_follow_the_spindle_gets_its_own_period(simulated, tmp_path):
    """The 55 Hz shaker on a machine whose spindle runs 3000 → 2400 → 3600 rpm: the spindle speed read from
    the samples is only a presumption. The period found in the data beats every spindle-locked model by
    far, so it is chosen (source "detected") and the tracker runs the time kernel at it; before, the
    spindle's periods were in play ahead of it (LS written with a spindle tracker, self-check alarm).
    Given by the user (--spindle-rpm) the spindle period is kept and the data's period only suggested."""
    def rpm(t):
        return np.where(t < 5.0, 3000.0, np.where(t < 10.0, 2400.0, 3600.0))

    trial = _with_spindle_column(simulated("shaker-constant", seed=4, duration=15.0), tmp_path / "spindle.mcap", rpm)
    model_path = tmp_path / "off.model.toml"
    code, doc, _ = run_identify(trial, output=model_path)
    assert code == 0
    assert doc["period"]["source"] == "detected" and doc["period"]["suggested"] is None
    assert doc["period"]["value"] == pytest.approx(SHAKER_PERIOD, rel=0.01)
    assert doc["chosen"] == "pl_lssvm" and doc["pl_lssvm"]["kernel"] == "locally_periodic"
    locked = max(c["log_evidence"] for c in doc["candidates"]
                 if c["kernel"] == "spindle" or any(c["period"] == pytest.approx(60.0 / r) for r in (3000, 2400, 3600)))
    assert doc["pl_lssvm"]["log_evidence"] > locked + 10
    assert any("does not follow the spindle" in n for n in doc["pl_lssvm"]["notes"] + doc["ls"]["notes"])
    errs = doc["truth"]["model_physical_error"]
    assert errs["inertia"] < 0.01 and errs["damping"] < 0.02
    assert doc["self_check"]["state"] == "ok", doc["self_check"]["summary"]
    model = load_model(model_path)
    assert model.tracker.kernel.kind == "locally_periodic"
    assert model.tracker.kernel.period == pytest.approx(SHAKER_PERIOD, rel=0.01)
    assert model.online.adaptation.min_speed == 0.0    # the simulated friction follows the law down to Ω

    code, doc, _ = run_identify(trial, "--spindle-rpm", 3000)  # the user's word: kept, the data's period suggested
    assert code == 0
    assert doc["period"]["source"] == "spindle" and doc["period"]["value"] == pytest.approx(0.02)
    assert doc["period"]["suggested"] == pytest.approx(SHAKER_PERIOD, rel=0.01)


def test_a_long_record_is_identified_whole_and_a_window_still_can_be(simulated):
    """A record of any length is identified (61 605 samples at 333 Hz were refused: the exact likelihood
    cost O(N²)); --start/--end identify a window (the self-check runs over the same window)."""
    path = simulated("shaker-control", seed=3, duration=185.0)  # 61 605 samples at 333 Hz
    code, doc, err = run_identify(path, "--method", "ls", "--no-tune")
    assert code == 0, err
    assert doc["model"]["physical"]["inertia"] == pytest.approx(doc["truth"]["physical"]["inertia"], rel=0.01)
    assert doc["self_check"]["state"] == "ok" and doc["self_check"]["reports"] in (119, 120)  # its first 120 s
    code, _, err = run_identify(path, "--start", 40, "--end", 30)
    assert code == 2 and "window start (40 s) must come before its end (30 s) (command line: --start, --end)" in err
    code, doc, err = run_identify(path, "--start", 5, "--end", 35, "--method", "ls", "--no-tune")
    assert code == 0, err
    assert any(n.startswith("identified on the window 5 … 34.99") for n in doc["ls"]["notes"])
    assert doc["self_check"]["state"] == "ok" and doc["self_check"]["reports"] in (29, 30)
    assert doc["model"]["physical"]["inertia"] == pytest.approx(doc["truth"]["physical"]["inertia"], rel=0.01)
    whole = read_trial(path)
    part = whole.window(5.0, 35.0)
    rel = part.t - whole.t[0]
    assert rel[0] >= 5.0 and rel[-1] < 35.0 and len(part) == 9990 and np.all(np.diff(part.seq) == 1)
    assert np.array_equal(part.truth.seq, part.seq) and part.truth.force.size == len(part)
    for start, end, match in ((35.0, 5.0, "must come before"), (500.0, None, "no sample between"),
                              (-1.0, None, "window start must be")):
        with pytest.raises(ValueError, match=match):
            whole.window(start, end)
    assert whole.window() is whole
    with pytest.raises(TrialTooLong, match=r"holds more than 1,000 samples, the most read into memory") as exc:
        read_trial(path, max_samples=1000)
    assert exc.value.limit == 1000


@pytest.mark.slow
def test_ten_minutes_are_identified_whole_within_the_short_trials_tolerances(simulated):
    """200 000 samples (10 min at 333 Hz; refused before: more than 60 000): tuned on the window with the most
    disturbance, evaluated on the whole; β within the tolerances of the 20 s shaker trials (the time against
    the 30 s target is benchmarks/identify_speed.py's)."""
    code, doc, err = run_identify(simulated("shaker-constant", seed=6, duration=600.0))
    assert code == 0, err
    assert doc["chosen"] == "pl_lssvm" and doc["pl_lssvm"]["kernel"] in ("locally_periodic", "locally_periodic_zero_mean")
    assert np.all(_rel(doc["pl_lssvm"]["beta"], doc["truth"]["beta"]) < 0.005)
    errs = doc["truth"]["model_physical_error"]
    assert errs["inertia"] < 0.01 and errs["damping"] < 0.02 and errs["coulomb"] < 0.05
    assert doc["checks"]["adequacy"]["adequate"] and doc["self_check"]["reports"] in (119, 120)


def test_without_o_the_model_goes_next_to_the_trial_and_is_never_overwritten(simulated, tmp_path, capsys):
    """``identify`` without -o did all the work and wrote nothing (exit 0). The model file now goes next to the
    trial (TRIAL.model.toml); when that file exists the command refuses at once, naming -o, before any work;
    --dry-run writes none."""
    import shutil

    trial = tmp_path / "axis.mcap"
    shutil.copy(simulated("shaker-control", duration=6.0), trial)
    default = tmp_path / "axis.model.toml"
    assert main(["identify", str(trial), "--method", "ls", "--no-tune"]) == 0
    assert f"wrote {default}" in capsys.readouterr().err.replace("\n", "")
    assert load_model(default).method == "ls"
    before = default.read_bytes()
    assert main(["identify", str(trial), "--method", "ls", "--no-tune"]) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "give -o to replace it" in err and "--dry-run" in err
    assert default.read_bytes() == before
    assert main(["identify", str(trial), "--method", "ls", "--no-tune", "--dry-run"]) == 0
    assert "wrote" not in capsys.readouterr().err and default.read_bytes() == before
    assert main(["identify", str(trial), "--dry-run", "-o", str(tmp_path / "x.toml")]) == 2
    assert "--dry-run and -o contradict" in capsys.readouterr().err


def test_json_document_has_exactly_the_documented_shape(simulated):
    code, doc, _ = run_identify(simulated("shaker-control", duration=20.0))
    assert code == 0 and set(doc) == JSON_KEYS
    assert set(doc["self_check"]) == {"state", "reports", "flagged", "reasons", "online", "summary"}
    assert doc["self_check"]["state"] == "ok" and doc["self_check"]["flagged"] == 0
    assert set(doc["period"]) == {"value", "source", "suggested"}
    assert doc["period"]["source"] == "none" and doc["period"]["value"] is None  # nothing periodic to find
    for c in doc["candidates"]:
        assert set(c) == {"method", "kernel", "period", "hyperparameters", "log_evidence", "valid", "why_not"}
    assert [c["method"] for c in doc["candidates"]] == ["ls", "pl_lssvm"]  # LS and the squared exponential
    assert set(doc["model"]) == {"method", "beta", "beta_se", "physical", "physical_se"}
    assert doc["chosen"] == "ls" and doc["model"]["beta"] == doc["ls"]["beta"]
    assert set(doc["model"]["physical"]) == PHYSICAL_KEYS == set(doc["model"]["physical_se"])
    assert all(s > 0 for s in doc["model"]["beta_se"])
    assert doc["error"] is None and set(doc["checks"]) >= {"noise", "omega", "process", "offset_separated", "low_speed",
                                                          "law_holds_above", "left_out", "min_speed", "adequacy",
                                                          "delay"}
    assert doc["checks"]["offset_separated"] is True and doc["checks"]["adequacy"]["adequate"]
    assert doc["checks"]["noise"]["sigma_n"] == pytest.approx(5e-6, rel=0.5)
    assert doc["model"]["physical"]["inertia"] == pytest.approx(doc["truth"]["physical"]["inertia"], rel=0.01)
    json.dumps(doc, allow_nan=False)  # strict JSON


def test_json_is_strict_for_a_drive_without_coulomb_friction(tmp_path):
    # a true β of 0 (no Coulomb friction) once gave a relative error of inf: `Infinity` in the JSON
    # document (not JSON) and a RuntimeWarning on stderr
    sc = load_scenario("shaker-control", {"drive": {"coulomb_pos": 0.0, "coulomb_neg": 0.0}}, duration=6.0)
    trial = tmp_path / "frictionless.mcap"
    write_trial(simulate(sc, seed=1), trial)
    code, doc, err = run_identify(trial, "--method", "ls", "--coulomb")
    assert code == 0 and doc["truth"]["physical"]["coulomb"] == 0.0
    assert "RuntimeWarning" not in err
    json.dumps(doc, allow_nan=False)  # strict JSON
    assert all(math.isfinite(x) for x in doc["truth"]["ls_beta_rel_error"])


def test_an_absurd_sample_is_named_not_called_collinear(simulated, tmp_path):
    # one v_ref of 1e300 m/s (a unit or recording fault) once ended in "columns 'v_ref' are collinear"
    import msgspec

    def spike(b):
        v = list(b.v_ref)
        if b.seq <= 250 < b.seq + len(v):
            v[250 - b.seq] = 1e300
        return msgspec.structs.replace(b, v_ref=v)

    bad = rewrite_samples(simulated("shaker-control", duration=6.0), tmp_path / "spike.mcap", spike)
    code, doc, err = run_identify(bad, "--method", "ls")
    assert code == 2 and "absurd magnitude" in doc["error"]
    assert "1 sample(s) with an absurd magnitude, first at seq 250" in err and "v_ref = 1e+300 m/s" in err
    assert "collinear" not in err and "Traceback" not in err


@pytest.mark.parametrize("gain", ["0", "-5", "nan"])
def test_a_loop_gain_that_is_not_a_gain_is_refused(simulated, gain):
    # --loop-gain 0 once ended in a ZeroDivisionError traceback, -5 in "Coulomb friction negative",
    # nan in a model-file error after the whole identification
    code, doc, err = run_identify(simulated("shaker-control", duration=6.0), "--method", "ls", "--loop-gain", gain)
    assert code == 2 and "Traceback" not in err and "loop_gain must be a positive number" in doc["error"]
    assert f"loop_gain must be a positive number (N·s/m), got {float(gain)!r}" in err
    assert err.rstrip().endswith("(command line: --loop-gain)")


def test_a_spindle_too_fast_for_the_sample_rate_is_left_out_not_fatal(tmp_path):
    # 19 000 rpm at 333 Hz: the spindle period (3.2 ms) is under two samples; the metadata speed once
    # refused the trial outright, even with --method ls (the samples' speed column was already skipped)
    sc = load_scenario("milling-dec", {"disturbance": {"spindle_rpm": 19000.0}}, duration=6.0)
    trial = tmp_path / "fast-spindle.mcap"
    write_trial(simulate(sc, seed=1), trial)
    assert read_trial(trial).meta.spindle_rpm == 19000.0
    code, doc, err = run_identify(trial, "--method", "ls")
    assert code == 0 and doc["period"]["source"] != "spindle", err
    assert any("60/19000 rpm = 0.00315789 s (trial metadata) is shorter than two samples" in n
               for n in doc["ls"]["notes"])
    assert doc["model"]["physical"]["inertia"] == pytest.approx(1500.0, rel=0.05)


def test_parameters_that_move_with_the_disturbance_model_are_not_a_valid_model(tmp_path):
    """Validity rule 3. Milling with the spindle at 300 rpm (5 Hz, inside the feed's band), J = 1500 kg: LS
    once gave J = 27 953 ± 4 501 kg and was chosen (self-check ok). The periodic candidates explain the
    data far better (log evidence +11 768), determine J better than LS, and put it 4.2 s.e. away — with
    a negative Coulomb friction (rule 1). No candidate is then a valid model: refused, not printed."""
    sc = load_scenario("milling-incdec", {"disturbance": {"spindle_rpm": 300.0}}, duration=20.0)
    trial = tmp_path / "slow-spindle.mcap"
    write_trial(simulate(sc, seed=3), trial)
    ident = identify(read_trial(trial))
    ls = ident.candidates[0]
    assert ident.chosen is None and ident.refusal.startswith("no candidate is a valid model of this drive")
    assert ls.why_not.startswith("biased by the disturbance it leaves out: PL-LSSVM, locally periodic")
    assert " puts inertia at " in ls.why_not
    assert "; LS: biased by the disturbance it leaves out" in ident.refusal  # the best's advice names LS
    witness = max(ident.candidates, key=lambda c: c.log_evidence)
    assert witness.log_evidence > ls.log_evidence + 1000 and "Coulomb friction negative" in witness.why_not
    from monitor.report import summary_columns  # the parameter table does not print them as the drive's

    assert summary_columns(ident)[1] == "LS — NOT VALID (see candidates)"
    assert summary_columns(ident)[2].startswith("PL-LSSVM (") and summary_columns(ident)[2].endswith("NOT VALID (see candidates)")


def test_metadata_ts_that_contradicts_the_sample_times_is_refused(simulated, tmp_path):
    # metadata Ts = 1 ms on samples 3 ms apart once gave J = 101.6 ± 0.29 kg (truth 300) and self-check "ok"
    import msgspec

    from feedio.mcapio import write_arrays

    src = read_trial(simulated("shaker-control", duration=6.0))
    bad = tmp_path / "wrong-ts.mcap"
    write_arrays(bad, msgspec.structs.replace(src.meta, Ts=0.001), dict(t=src.t, v_ref=src.v_ref, v_meas=src.v_meas),
                 start=0)
    code, doc, err = run_identify(bad, "--method", "ls")
    assert code == 2 and "Traceback" not in err
    assert "the samples are 0.003003 s apart but the trial's metadata give Ts = 0.001 s" in err
    # --json: one document on stdout all the same, every key there, the error in it (it printed nothing)
    assert set(doc) == JSON_KEYS and "the samples are 0.003003 s apart" in doc["error"]
    assert all(doc[k] is None for k in JSON_KEYS - {"error"})


def test_without_loop_gain_only_ratios(simulated):
    trial = read_trial(simulated("shaker-control", duration=20.0))
    trial.meta.loop_gain = None
    ident = identify(trial, method="ls", tune=False)
    assert set(ident.ls.physical) == {f"{k}_over_gain" for k in PHYSICAL_KEYS}
    assert any("only J/K" in n for n in ident.notes)


def test_model_file_and_report(simulated, tmp_path):
    model_path = tmp_path / "axis.model.toml"
    report = tmp_path / "report"
    trial = simulated("shaker-constant", duration=20.0)
    assert main(["identify", str(trial), "--period", str(SHAKER_PERIOD), "-o", str(model_path),
                 "--report", str(report)]) == 0
    model = load_model(model_path)
    assert model.form == "velocity-loop" and model.coulomb and model.beta_names[-1] == "one"
    assert model.tracker.kernel.period == pytest.approx(SHAKER_PERIOD)
    assert model.identification["chosen"] == "pl_lssvm" and len(model.candidates) >= 4
    assert len(model.provenance["sha256"]) == 64 and model.validity_warning is None
    pngs = list(report.glob("*.png"))
    assert len(pngs) == 1 and pngs[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and pngs[0].stat().st_size > 50_000
    md = next(report.glob("*.md")).read_text()
    assert "**Chosen model: PL-LSSVM" in md and "| LS |" in md and "log evidence" in md
    assert "disturbance correlation with the truth" in md and "vs truth" in md
    assert "## Self-check" in md and model.identification["self_check"] in md   # the same verdict as the file
    assert model.identification["self_check"].startswith("ok: ")


def test_invalid_model_refused_unless_forced_and_run_refuses_it(emps_trials, tmp_path, capsys):
    """The thesis' PL-LSSVM at ψ = 1 s on the clean EMPS trial takes the Coulomb friction (it competes with
    sign(v)): asked for explicitly it is refused (exit 1, nothing written); --force writes it with the
    warning in the file and 'feedmon run' refuses the file with that reason."""
    trial = emps_trials["plain"]
    refused = tmp_path / "refused.toml"
    argv = ["identify", str(trial), "--method", "pl-lssvm", "--period", "1", "--no-tune"]
    assert main([*argv, "-o", str(refused)]) == 1
    err = capsys.readouterr().err
    assert "no PL-LSSVM candidate is a valid model" in err and "competes" in err and "Nothing written" in err
    assert not refused.exists()
    forced = tmp_path / "forced.toml"
    assert main([*argv, "-o", str(forced), "--force"]) == 0
    text = forced.read_text()
    assert "[validity]" in text and "--force" in text
    assert load_model(forced, allow_invalid=True).validity_warning.startswith("written with --force")
    out = tmp_path / "est.mcap"
    assert main(["run", "--from", str(trial), "-o", str(out), "--model", str(forced)]) == 2
    err = capsys.readouterr().err
    assert "forced.toml" in err and "validity.warning" in err and "competes" in err


def test_clear_errors(simulated, capsys):
    trial = simulated("shaker-control", duration=20.0)
    assert main(["identify", str(trial), "--period", "0.02", "--spindle-rpm", "3000"]) == 2
    assert "--period and --spindle-rpm" in capsys.readouterr().err
    assert main(["identify", str(trial), "--period", "1e-5"]) == 2
    assert "shorter than two samples" in capsys.readouterr().err
    assert main(["identify", str(simulated("milling-inc")), "--coulomb"]) == 2
    err = capsys.readouterr().err
    assert "-sigma_n" in err and "use coulomb=False" in err and "(command line: --coulomb/--no-coulomb)" in err
    assert main(["identify", str(trial), "--period", "1e-5"]) == 2
    assert capsys.readouterr().err.rstrip().endswith("(command line: --period)")


def test_options_that_cannot_work_are_refused_before_the_identification(simulated, tmp_path, capsys):
    """--teeth 0 was accepted; -o into a missing or read-only place and --report onto a file failed only
    after the whole identification (minutes), --report with a raw '[Errno 17]'; --omega 1e9 only when
    saving the model. Each is now refused at once, naming the option, and nothing is written."""
    trial = str(simulated("shaker-control", duration=20.0))
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    for argv, says in ((["--teeth", "0"], "--teeth must be the tool's number of cutting edges, 1 … 1000, got 0"),
                       (["-o", str(tmp_path / "missing" / "m.toml")], "does not exist; create it first"),
                       (["-o", str(tmp_path)], "is a directory; give the model file's name"),
                       (["--report", str(a_file)], "is a file; give a directory"),
                       (["--omega", "1e9"], "omega must be a dead band 0 … 10 m/s, got 1000000000.0")):
        assert main(["identify", trial, *argv]) == 2, argv
        err = capsys.readouterr().err
        assert says in err and "Traceback" not in err and "Errno" not in err, (argv, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file"]


@pytest.mark.parametrize(("kwargs", "parameter", "flag", "text"), [
    ({"omega": -1.0}, "omega", "--omega", "omega must be a dead band 0 … 10 m/s, got -1.0"),
    ({"period": 1e-5}, "period", "--period", "period: period 1e-05 s is shorter than two samples"),
    ({"spindle_rpm": -5.0}, "spindle_rpm", "--spindle-rpm", "spindle_rpm must be positive, got -5.0"),
    ({"sigma2": 0.0}, "sigma2", "--sigma2", "sigma2 must be a positive number, got 0.0"),
])
def test_a_bad_argument_names_the_parameter_and_the_cli_names_the_flag(simulated, capsys, kwargs, parameter, flag,
                                                                        text):
    """style.md, library vs CLI: identify() names its parameter (never a flag); ``feedmon identify`` with the
    same bad value exits 2 with the same message and the flag that sets it."""
    trial_path = simulated("shaker-control", duration=20.0)
    with pytest.raises(ParameterError) as err:
        identify(read_trial(trial_path), **kwargs)
    assert err.value.parameters == (parameter,) and text in str(err.value) and "--" not in str(err.value)
    assert isinstance(err.value, ValueError)  # existing `except ValueError` callers keep working
    value = next(iter(kwargs.values()))
    assert main(["identify", str(trial_path), flag, str(value), "--no-tune", "--method", "ls"]) == 2
    out = capsys.readouterr().err
    assert out.startswith("feedmon identify: error: ") and text in out and f"(command line: {flag})" in out


def test_a_failing_periodic_tune_stops_the_squared_exponential_one(simulated):
    """The squared-exponential candidate is tuned on a second thread beside the periodic ones: when the
    identification fails on this thread, the error reaches the caller and the second thread stops after
    its current evaluation (no tuning thread outlives ``identify``); a stop asked by the caller's own
    progress callback is one such failure."""
    import threading

    trial = read_trial(simulated("shaker-constant", seed=3, duration=6.0))
    seen: dict[str, int] = {}

    class Stop(Exception):
        pass

    def progress(label, done, total):
        assert 0 < done <= total
        seen[label] = seen.get(label, 0) + 1
        if label.startswith("locally periodic") and seen[label] == 2:
            raise Stop(label)

    with pytest.raises(Stop):
        identify(trial, period=SHAKER_PERIOD, progress=progress)
    assert seen[f"locally periodic ψ = {SHAKER_PERIOD:.6g} s"] == 2  # the failure came from the periodic tune
    assert not [t for t in threading.enumerate() if t.name.startswith("identify-beside")]
