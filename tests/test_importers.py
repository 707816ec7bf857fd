"""Importers: the real EMPS drive (key real-data check) and CSV exports."""


import numpy as np
import pytest

from feedio.mcapio import read_trial
from feedmon.cli import main
from kernels.errors import ParameterError
from kernels.feed_drive import beta_to_physical, regressors
from kernels.least_squares import least_squares
from replay.importers import EMPS_REFERENCE, load_emps, read_csv_trial

OMEGA = 1e-3  # Coulomb dead band for the EMPS (m/s)


@pytest.fixture(scope="module")
def emps_trial(tmp_path_factory, emps_file):
    out = tmp_path_factory.mktemp("emps") / "emps.mcap"
    assert main(["import", "emps", str(emps_file("DATA_EMPS.mat")), "-o", str(out)]) == 0
    return read_trial(out)


def test_emps_ls_identifies_published_parameters(emps_trial):
    tr = emps_trial
    assert tr.form == "force-input" and tr.Ts == pytest.approx(0.003, rel=1e-4) and len(tr) == 8280
    reg = regressors("force-input", tr.v_meas, u=tr.u, omega=OMEGA)
    p = beta_to_physical("force-input", least_squares(reg.Z, reg.y).beta, tr.Ts)
    fc = 0.5 * (p.coulomb_pos + p.coulomb_neg)  # symmetric Coulomb friction
    offset = p.offset + 0.5 * (p.coulomb_pos - p.coulomb_neg)  # the published model's offset
    ref = EMPS_REFERENCE
    print(f"\nEMPS LS: M {p.inertia:.2f} kg, Fv {p.damping:.1f} N·s/m, Fc {fc:.2f} N, offset {offset:.2f} N")
    assert p.inertia == pytest.approx(ref["M"], rel=0.01)
    assert p.damping == pytest.approx(ref["Fv"], rel=0.03)
    assert fc == pytest.approx(ref["Fc"], rel=0.03)
    assert offset == pytest.approx(ref["offset"], abs=0.5)


def test_emps_1khz(tmp_path, emps_file):
    out = tmp_path / "emps1k.mcap"
    assert main(["import", "emps", str(emps_file("DATA_EMPS.mat")), "-o", str(out), "--rate", "1000"]) == 0
    tr = read_trial(out)
    assert tr.Ts == pytest.approx(0.001, rel=1e-4) and len(tr) == 24840
    reg = regressors("force-input", tr.v_meas, u=tr.u, omega=OMEGA)
    p = beta_to_physical("force-input", least_squares(reg.Z, reg.y).beta, tr.Ts)
    assert p.inertia == pytest.approx(EMPS_REFERENCE["M"], rel=0.03)


def test_emps_pulses_truth(tmp_path, emps_file):
    out = tmp_path / "pulses.mcap"
    assert main(["import", "emps", str(emps_file("DATA_EMPS_PULSES.mat")), "-o", str(out)]) == 0
    tr = read_trial(out)
    assert tr.truth is not None and tr.channels == ["/emps/X/samples", "/emps/X/truth"]
    on = tr.truth.force < -100  # T_c sign: the pulse pushes in the + direction
    assert 0.3 < on.mean() < 0.7
    assert -tr.truth.force.min() == pytest.approx(35.15065 * 1.014 * 5, rel=1e-3)
    assert np.all(tr.truth.f[on] > 0)
    # the PD-law command identifies the same drive even though the pulses are not in u
    reg = regressors("force-input", tr.v_meas, u=tr.u - tr.truth.force, omega=OMEGA)
    p = beta_to_physical("force-input", least_squares(reg.Z, reg.y).beta, tr.Ts)
    assert p.inertia == pytest.approx(EMPS_REFERENCE["M"], rel=0.02)


def test_emps_bad_input(tmp_path, capsys):
    junk = tmp_path / "junk.mat"
    junk.write_bytes(b"not a mat file at all" * 10)
    assert main(["import", "emps", str(junk), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "junk.mat is not a MATLAB .mat file" in capsys.readouterr().err
    assert main(["import", "emps", str(tmp_path / "missing.mat"), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "nonlinearbenchmark.org" in capsys.readouterr().err


CSV = "time;vr;vm;F;I\n" + "".join(
    f"{k * 3};{600.0 + k};{590.0 + k};{0.1 * k};{0.01 * k}\n" for k in range(50)
)


def test_csv_import_units(tmp_path):
    src = tmp_path / "ctl.csv"
    src.write_text(CSV)
    out = tmp_path / "ctl.mcap"
    rc = main(["import", "csv", str(src), "-o", str(out), "--map", "t=time,v_ref=vr,v_meas=vm,u=F,current=I",
               "--units", "t=ms,v_ref=mm/min,v_meas=mm/min,u=kN", "--machine", "dmu", "--axis", "Y",
               "--loop-gain", "5e4"])
    assert rc == 0
    tr = read_trial(out)
    assert (tr.machine, tr.axis) == ("dmu", "Y") and tr.meta.loop_gain == 5e4
    assert tr.Ts == pytest.approx(0.003)
    np.testing.assert_allclose(tr.t, np.arange(50) * 0.003)
    np.testing.assert_allclose(tr.v_ref, (600.0 + np.arange(50)) / 60000.0)
    np.testing.assert_allclose(tr.u, 100.0 * np.arange(50))
    np.testing.assert_allclose(tr.current, 0.01 * np.arange(50))
    assert tr.meta.provenance.source == "csv"


def test_csv_missing_column_lists_available(tmp_path, capsys):
    src = tmp_path / "ctl.csv"
    src.write_text(CSV)
    with pytest.raises(ValueError, match=r"ctl\.csv: column 'v_actual' \(for v_meas\) not found; available columns: 'time', 'vr', 'vm', 'F', 'I'"):
        read_csv_trial(src, "t=time,v_ref=vr,v_meas=v_actual")
    rc = main(["import", "csv", str(src), "-o", str(tmp_path / "o.mcap"), "--map", "t=time,v_ref=vr,v_meas=nope"])
    assert rc == 2 and "'nope' (for v_meas) not found" in capsys.readouterr().err
    with pytest.raises(ValueError, match="v_meas=N: N is a force unit, v_meas needs a velocity unit"):
        read_csv_trial(src, "t=time,v_ref=vr,v_meas=vm", "v_meas=N")
    with pytest.raises(ValueError, match="must give the column of u"):
        read_csv_trial(src, "t=time,v_meas=vm", form="force-input")


@pytest.mark.parametrize(("kwargs", "parameter", "flag", "text"), [
    ({"units": "v_meas=parsec"}, ("units",), "--units", "units v_meas=parsec: unknown unit; known: s, ms"),
    ({"units": "v_meas=N"}, ("units",), "--units", "units v_meas=N: N is a force unit, v_meas needs a velocity unit"),
    ({"mapping": "t=time,v_meas=vm"}, ("mapping", "form"), "--map, --form",
     "mapping must give the column of v_ref for the velocity-loop form (form='velocity-loop' needs v_ref, "
     "form='force-input' needs u)"),
    ({"mapping": "t=time,speed=vm"}, ("mapping",), "--map", "mapping: unknown field 'speed'; fields: t, v_ref"),
    ({"form": "force-input"}, ("form", "mapping"), "--form, --map",
     "mapping gives v_ref (a velocity reference) and no u: that is the velocity-loop form"),
    # a force command mapped without --form: the error names the form (it once named v_ref only)
    ({"mapping": "t=time,v_meas=vm,u=F"}, ("form", "mapping"), "--form, --map",
     "mapping gives u (a force command) and no v_ref: that is the force-input form; set form='force-input'"),
    # a time column read in the wrong unit (seconds as ms gave Ts = 3 µs, silently): here ms read as s
    ({"units": "t=s,v_ref=mm/min,v_meas=mm/min"}, ("units",), "--units", "the median time step is 3 s (t read in s), outside the 1e-05 … 1 s a "
                                             "machine-tool controller samples at: check the unit of the time column; "
                                             "if the column is in ms, say units t=ms"),
])
def test_a_bad_argument_names_the_parameter_and_the_cli_names_the_flag(tmp_path, capsys, kwargs, parameter, flag,
                                                                        text):
    """style.md, library vs CLI: read_csv_trial names its parameter (never a flag); ``feedmon import csv`` with
    the same bad option exits 2 with the same message and the flag."""
    src = tmp_path / "ctl.csv"
    src.write_text(CSV)
    args = {"mapping": "t=time,v_ref=vr,v_meas=vm", "units": None, "form": "velocity-loop"} | kwargs
    with pytest.raises(ParameterError) as err:
        read_csv_trial(src, args["mapping"], args["units"], form=args["form"])
    assert err.value.parameters == parameter and text in str(err.value) and "--" not in str(err.value)
    argv = ["import", "csv", str(src), "-o", str(tmp_path / "o.mcap"), "--map", args["mapping"], "--form", args["form"]]
    assert main(argv + (["--units", args["units"]] if args["units"] else [])) == 2
    out = capsys.readouterr().err
    assert out.startswith("feedmon import: error: ") and text in out and f"(command line: {flag})" in out
    assert not (tmp_path / "o.mcap").exists()


def test_emps_rate_names_the_parameter(tmp_path):
    with pytest.raises(ParameterError, match=r"^rate must be 333 or 1000 \(Hz\), got 500$"):
        load_emps(tmp_path / "DATA_EMPS.mat", rate=500)
    bad = tmp_path / "bad.csv"
    bad.write_text("time,vr,vm\n0,1,1\n1,x,1\n2,1,1\n")
    with pytest.raises(ValueError, match=r"line 3, column 'vr' \(for v_ref\): 'x' is not a number"):
        read_csv_trial(bad, "t=time,v_ref=vr,v_meas=vm")


def test_csv_gap_other_rate_and_absurd_values_are_refused(tmp_path, capsys):
    # rows 20…29 lost: the rows before and after the gap would pose as consecutive samples of the
    # drive's difference equation (a 3 s gap once gave J −4 %, B −20 %, Coulomb +60 % "ok")
    rows = [f"{k * 0.003:.6f},0.01,{0.0099 + 1e-4 * (k % 3)}" for k in range(60) if not 20 <= k < 30]
    gap = tmp_path / "gap.csv"
    gap.write_text("time,vr,vm\n" + "\n".join(rows) + "\n")
    out = tmp_path / "o.mcap"
    assert main(["import", "csv", str(gap), "-o", str(out), "--map", "t=time,v_ref=vr,v_meas=vm"]) == 2
    err = capsys.readouterr().err
    assert "gap.csv: the time step from line 21 to 22 is 0.033 s, not the sampling time Ts = 0.003 s" in err
    assert "Traceback" not in err and not out.exists()
    with pytest.raises(ValueError, match=r"the time step from line 2 to 3 is 0\.003 s, not the sampling time Ts = 0\.001 s"):
        read_csv_trial(gap, "t=time,v_ref=vr,v_meas=vm", Ts=0.001)
    with pytest.raises(ValueError, match="^Ts must be a positive number of seconds, got -1"):
        read_csv_trial(gap, "t=time,v_ref=vr,v_meas=vm", Ts=-1.0)
    with pytest.raises(ValueError, match=r"^loop_gain must be a positive number \(N·s/m\), got 0\.0"):
        read_csv_trial(gap, "t=time,v_ref=vr,v_meas=vm", loop_gain=0.0)  # identify once divided by it
    big = tmp_path / "big.csv"
    big.write_text("time,vr,vm\n" + "".join(f"{k * 0.003:.6f},{'1e300' if k == 7 else '0.01'},0.0099\n" for k in range(20)))
    with pytest.raises(ValueError, match=r"big\.csv, line 9, column 'vr' \(for v_ref\): 1e\+300 \(1e\+300 m/s\) is "
                                         r"beyond the 50 m/s"):
        read_csv_trial(big, "t=time,v_ref=vr,v_meas=vm")
    ok = tmp_path / "ok.csv"  # jitter of a logger's clock, an empty (missing) cell: still one trial
    ok.write_text("time,vr,vm\n" + "".join(f"{k * 0.003 + (0.0004 if k % 2 else 0):.6f},{'' if k == 5 else 0.01},0.0099\n"
                                           for k in range(20)))
    tr = read_csv_trial(ok, "t=time,v_ref=vr,v_meas=vm")
    assert len(tr) == 20 and np.isnan(tr.v_ref[5])


def test_csv_that_is_not_csv_text_is_named_not_a_traceback(tmp_path, capsys):
    # a field beyond csv.field_size_limit once escaped as `_csv.Error` (a traceback); bytes that are
    # not UTF-8 gave a bare "'utf-8' codec can't decode …" without the file
    long = tmp_path / "long.csv"
    long.write_text("time,vr,vm\n0," + "x" * 300_000 + ",0\n0.003,0,0\n0.006,0,0\n")
    binary = tmp_path / "binary.csv"
    binary.write_bytes(b"\xff\xfe\x00time,vr,vm\n")
    for src, says in ((long, "long.csv, line 2: not a readable CSV text file (field larger than field limit"),
                      (binary, "binary.csv: not a readable CSV text file ('utf-8' codec can't decode")):
        out = tmp_path / "o.mcap"
        assert main(["import", "csv", str(src), "-o", str(out), "--map", "t=time,v_ref=vr,v_meas=vm"]) == 2
        err = capsys.readouterr().err
        assert says in err and "Traceback" not in err and not out.exists(), err


def test_csv_beyond_the_trial_sample_limit_is_refused_naming_the_line(tmp_path, monkeypatch):
    """Every row is kept in memory while importing (a 92 MB CSV once took 700 MB): beyond
    MAX_TRIAL_SAMPLES rows (10 M; lowered to 5 here) the import stops at that line."""
    import replay.importers as imp

    monkeypatch.setattr(imp, "MAX_TRIAL_SAMPLES", 5)
    path = tmp_path / "long.csv"
    path.write_text("time,vr,vm\n" + "".join(f"{k * 0.003:.6f},0.01,0.0099\n" for k in range(8)))
    with pytest.raises(ValueError, match=r"long\.csv, line 7: more than 5 data rows, the most one trial file holds"):
        read_csv_trial(path, "t=time,v_ref=vr,v_meas=vm")
    path.write_text("time,vr,vm\n" + "".join(f"{k * 0.003:.6f},0.01,0.0099\n" for k in range(5)))
    assert len(read_csv_trial(path, "t=time,v_ref=vr,v_meas=vm").t) == 5
