"""Model file: round trip and validation with messages that name the key and the file."""

import math

import pytest

from kernels import LocallyPeriodic
from monitor.model_file import AxisModel, ModelFileError, TrackerConfig, load_model, save_model


def _model(**overrides) -> AxisModel:
    base = dict(
        machine="mill",
        axis="x",
        form="velocity-loop",
        Ts=1 / 333,
        beta=[0.8338, 0.1632, -1.02e-4, 1.03e-4],
        omega=5e-4,
        coulomb=True,
        loop_gain=None,
        tracker=TrackerConfig(kernel=LocallyPeriodic(1.2, 0.495, 1 / 55).to_dict()),
        physical={"inertia_over_gain": 0.0123, "damping_over_gain": 0.004},
        identification={"sigma1": 0.59, "sigma2": 0.42, "gamma": 50.3, "period": 1 / 55, "tuned": False},
        provenance={"source": "trial.mcap", "sha256": "ab" * 32, "method": "pl-lssvm", "feedmon_version": "0.1.0"},
    )
    base.update(overrides)
    return AxisModel(**base)


def test_round_trip_is_exact(tmp_path):
    model = _model()
    path = save_model(model, tmp_path / "x.model.toml")
    back = load_model(path)
    assert back.beta == model.beta
    assert back.Ts == model.Ts
    assert back.tracker == model.tracker
    assert back.tracker.build_kernel() == LocallyPeriodic(1.2, 0.495, 1 / 55)
    assert back.physical == model.physical
    assert back.identification == model.identification
    assert back.provenance == model.provenance
    assert back.beta_names == ("v_ref", "v_meas", "-sigma_p", "-sigma_n")
    assert not back.force_scalable and back.force_gain is None


def test_force_input_model_scales_to_newtons(tmp_path):
    model = _model(form="force-input", beta=[3.1e-5, 0.9936, 6.4e-4, -6.4e-4, 9.9e-5])
    back = load_model(save_model(model, tmp_path / "m.toml"))
    assert back.force_scalable and math.isclose(back.force_gain, 3.1e-5)


def test_file_is_human_readable_toml_with_units(tmp_path):
    text = save_model(_model(), tmp_path / "m.toml").read_text()
    assert "format_version = 1" in text
    assert "[tracker]" in text and "forgetting = 0.998" in text  # the measured default (monitor.online_settings)
    assert "# s" in text  # units next to values


def _write(tmp_path, text):
    p = tmp_path / "bad.model.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "mutate, key, problem",
    [
        (lambda t: t.replace("format_version = 1", "format_version = 7"), "format_version", "unknown version"),
        (lambda t: t.replace('form = "velocity-loop"', 'form = "torque"'), "model.form", "unknown input form"),
        (lambda t: t.replace("gamma = 5.85", 'gamma = "high"'), "tracker.gamma", "must be a number"),
        (lambda t: t.replace("gamma = 5.85", "gamma = nan"), "tracker.gamma", "must be finite"),
        (lambda t: t.replace("gamma = 5.85\n", ""), "tracker.gamma", "missing"),
        (lambda t: t.replace("forgetting = 0.998", "forgetting = 1.5"), "tracker.forgetting", "(0, 1]"),
        (lambda t: t.replace("budget = 100", "budget = 0"), "tracker.budget", "≥ 1"),
        (lambda t: t.replace("beta = [0.8338, 0.1632,", "beta = [0.8338,"), "model.beta", "needs 4"),
        (lambda t: t.replace("Ts = ", "Ts = -"), "model.Ts", "> 0"),
        (lambda t: t.replace('kernel = "locally_periodic"', 'kernel = "spline"'), "tracker.kernel", "unknown kernel type"),
    ],
)
def test_bad_model_files_name_key_and_file(tmp_path, mutate, key, problem):
    good = save_model(_model(), tmp_path / "good.toml").read_text()
    bad = mutate(good)
    assert bad != good, "mutation did not apply"
    path = _write(tmp_path, bad)
    with pytest.raises(ModelFileError) as err:
        load_model(path)
    message = str(err.value)
    assert str(path) in message and key in message and problem in message


def test_not_toml_and_missing_file(tmp_path):
    with pytest.raises(ModelFileError, match="not a valid TOML"):
        load_model(_write(tmp_path, "\x00\x01 this is = = not toml"))
    with pytest.raises(ModelFileError, match="feedmon identify"):
        load_model(tmp_path / "absent.toml")


def test_non_finite_numbers_refused_when_saving(tmp_path):
    with pytest.raises(ValueError, match="finite"):
        save_model(_model(physical={"inertia": float("inf")}), tmp_path / "m.toml")
