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
    ({"units": "v_meas=parsec"}, "units", "--units", "units v_meas=parsec: unknown unit; known: s, ms"),
    ({"units": "v_meas=N"}, "units", "--units", "units v_meas=N: N is a force unit, v_meas needs a velocity unit"),
    ({"mapping": "t=time,v_meas=vm"}, "mapping", "--map", "mapping must give the column of v_ref for the "
                                                          "velocity-loop form"),
    ({"mapping": "t=time,speed=vm"}, "mapping", "--map", "mapping: unknown field 'speed'; fields: t, v_ref"),
    ({"form": "force-input"}, "mapping", "--map", "mapping must give the column of u for the force-input form"),
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
    assert err.value.parameters == (parameter,) and text in str(err.value) and "--" not in str(err.value)
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
