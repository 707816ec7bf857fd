"""Model file: round trip (version 2), version-1 files, documented ranges checked on load with messages
naming the file and the key, and models that cannot be right refused."""

import math

import numpy as np
import pytest

from kernels import LocallyPeriodic
from kernels.feed_drive import physical_to_beta
from monitor.model_file import AxisModel, ModelFileError, TrackerConfig, load_model, ranges_table, save_model
from monitor.online_settings import (
    LocallyPeriodicKernel,
    PeriodicKernel,
    SpindleKernel,
    SquaredExponentialKernel,
    ZeroMeanLocallyPeriodicKernel,
)

BETA = [0.8338, 0.1632, 1.02e-4, -1.03e-4]  # velocity loop: stable pole, positive Coulomb friction


def _model(**overrides) -> AxisModel:
    base = dict(
        machine="mill",
        axis="x",
        form="velocity-loop",
        Ts=1 / 333,
        beta=list(BETA),
        omega=5e-4,
        coulomb=True,
        loop_gain=None,
        tracker=TrackerConfig(kernel=LocallyPeriodicKernel(sigma1=1.2, sigma2=0.495, period=1 / 55)),
        physical={"inertia_over_gain": 0.0123, "damping_over_gain": 0.004},
        physical_se={"inertia_over_gain": 1e-5, "damping_over_gain": 2e-5},
        identification={"sigma1": 0.59, "sigma2": 0.42, "gamma": 50.3, "period": 1 / 55, "tuned": False,
                        "chosen": "pl_lssvm", "kernel": "locally_periodic", "period_source": "given",
                        "log_evidence": 1234.5},
        candidates=[{"method": "ls", "kernel": "none", "period": None, "log_evidence": 1000.0, "valid": True,
                     "why_not": ""},
                    {"method": "pl_lssvm", "kernel": "locally_periodic", "period": 1 / 55, "log_evidence": 1234.5,
                     "valid": True, "why_not": ""}],
        beta_se=[1e-4, 1e-4, 1e-6, 1e-6],
        provenance={"source": "trial.mcap", "sha256": "ab" * 32, "method": "pl-lssvm", "feedmon_version": "0.1.0"},
    )
    base.update(overrides)
    return AxisModel(**base)


def test_round_trip_is_exact(tmp_path):
    model = _model()
    path = save_model(model, tmp_path / "x.model.toml")
    back = load_model(path)
    assert back.beta == model.beta and back.beta_se == model.beta_se
    assert back.Ts == model.Ts
    assert back.tracker == model.tracker
    assert back.tracker.build_kernel() == LocallyPeriodic(1.2, 0.495, 1 / 55)
    assert back.physical == model.physical and back.physical_se == model.physical_se
    assert back.identification == {k: v for k, v in model.identification.items()}
    assert [c["log_evidence"] for c in back.candidates] == [1000.0, 1234.5]
    assert back.candidates[1]["period"] == pytest.approx(1 / 55)
    assert back.provenance == model.provenance
    assert back.beta_names == ("v_ref", "v_meas", "-sigma_p", "-sigma_n")
    assert not back.intercept and not back.force_scalable and back.force_gain is None
    assert back.validity_warning is None


def test_velocity_loop_with_intercept_keeps_the_constant(tmp_path):
    beta = BETA + [2e-5]
    back = load_model(save_model(_model(beta=beta, beta_se=None), tmp_path / "m.toml"))
    assert back.beta_names[-1] == "one" and back.intercept and back.beta == beta


def test_force_input_model_scales_to_newtons(tmp_path):
    model = _model(form="force-input", beta=[3.1e-5, 0.9936, 6.4e-4, -6.4e-4, 9.9e-5], beta_se=None)
    back = load_model(save_model(model, tmp_path / "m.toml"))
    assert back.force_scalable and math.isclose(back.force_gain, 3.1e-5) and back.intercept


def test_file_is_human_readable_toml_with_units_and_ranges_documented(tmp_path):
    text = save_model(_model(), tmp_path / "m.toml").read_text()
    assert "format_version = 2" in text
    assert "[tracker]" in text and "forgetting = 0.998" in text and "[physical_se]" in text
    assert "[[identification.candidates]]" in text
    assert "# s" in text  # units next to values
    table = ranges_table()
    for key in ("model.Ts", "tracker.budget", "tracker.jitter", "tracker.period", "tracker.sigma1", "format_version"):
        assert f"`{key}`" in table
    import monitor.model_file as mf
    assert table in mf.__doc__  # the module docstring documents every range


def test_version_1_files_are_still_read(tmp_path):
    v1 = """format_version = 1
[axis]
machine = "mill"
axis = "x"
[model]
form = "velocity-loop"
Ts = 0.003003003003003003
beta = [0.8338, 0.1632]
beta_names = ["v_ref", "v_meas"]
omega = 0.0005
coulomb = false
loop_gain = 83300.0
method = "pl-lssvm"
[physical]
inertia = 300.0
damping = 300.0
gain = 83300.0
inertia_over_gain = 0.0036
damping_over_gain = 0.0036
[tracker]
kernel = "locally_periodic"
sigma1 = 1.2
sigma2 = 0.495
period = 0.01818
gamma = 5.85
forgetting = 0.996
budget = 100
jitter = 1e-06
[identification]
sigma1 = 0.59
sigma2 = 0.42
period = 0.01818
gamma = 50.3
tuned = false
log_likelihood = 1000.0
[provenance]
source = "trial.mcap"
"""
    p = tmp_path / "v1.toml"
    p.write_text(v1)
    m = load_model(p)
    assert m.beta == [0.8338, 0.1632] and m.loop_gain == 83300.0 and m.physical["gain"] == 83300.0
    assert m.beta_se is None and m.physical_se == {} and m.candidates == []


def _write(tmp_path, text):
    p = tmp_path / "bad.model.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "mutate, key, problem",
    [
        (lambda t: t.replace("format_version = 2", "format_version = 7"), "format_version", "unknown version"),
        (lambda t: t.replace("format_version = 2", "format_version = true"), "format_version", "unknown version"),
        (lambda t: t.replace("format_version = 2", "format_version = 1.0"), "format_version", "unknown version"),
        (lambda t: t.replace('form = "velocity-loop"', 'form = "torque"'), "model.form", "Invalid enum value"),
        (lambda t: t.replace("gamma = 5.85", 'gamma = "high"'), "tracker.gamma", "Expected `float`"),
        (lambda t: t.replace("gamma = 5.85", "gamma = nan"), "tracker.gamma", "≥ 0.0001"),
        (lambda t: t.replace("gamma = 5.85\n", ""), "tracker.gamma", "missing"),
        (lambda t: t.replace("forgetting = 0.998", "forgetting = 1.5"), "tracker.forgetting", "≤ 1"),
        (lambda t: t.replace("budget = 100", "budget = 0"), "tracker.budget", "≥ 4"),
        (lambda t: t.replace("budget = 100", "budget = 3"), "tracker.budget", "≥ 4"),
        # issue 9 item 11: values that crashed, hung or ate memory
        (lambda t: t.replace("budget = 100", "budget = 1000000000"), "tracker.budget", "≤ 2000"),
        (lambda t: t.replace("budget = 100", "budget = 4096"), "tracker.budget", "≤ 2000"),  # 94 samples/s
        (lambda t: t.replace("sigma1 = 1.2", "sigma1 = 1e-300"), "tracker.sigma1", "≥ 1e-06"),
        (lambda t: t.replace("jitter = 1e-06", "jitter = 1e300"), "tracker.jitter", "≤ 0.1"),
        # a jitter of 0 made the tracker divide by γ² = 0, 1e-10 / 1e-12 broke its numerics down (NaN, 1e47)
        (lambda t: t.replace("jitter = 1e-06", "jitter = 0.0"), "tracker.jitter", "≥ 1e-08"),
        (lambda t: t.replace("jitter = 1e-06", "jitter = 1e-10"), "tracker.jitter", "≥ 1e-08"),
        (lambda t: t.replace("period = 0.01818", "period = 1e-300"), "tracker.period", "≥ 1e-06"),
        (lambda t: t.replace("beta = [0.8338, 0.1632,", "beta = [0.8338,"), "model.beta", "needs 4 or 5"),
        (lambda t: t.replace("Ts = ", "Ts = -"), "model.Ts", "≥ 1e-06"),
        (lambda t: t.replace("Ts = 0.003003003003003003", "Ts = inf"), "model.Ts", "≤ 10"),
        (lambda t: t.replace('kernel = "locally_periodic"', 'kernel = "spline"'), "tracker.kernel", "Invalid value"),
        (lambda t: t.replace('machine = "mill"', 'machine = "mill/*"'), "axis.machine", "regex"),
        (lambda t: t.replace("[tracker]\n", "[tracker]\ngama = 3.0\n"), "tracker.gama", "unknown key"),
        (lambda t: t.replace("omega = 0.0005", "omega = 0.0005\nomega_typo = 1"), "model.omega_typo", "unknown key"),
    ],
)
def test_bad_model_files_name_key_and_file(tmp_path, mutate, key, problem):
    good = save_model(_model(), tmp_path / "good.toml").read_text()
    good = good.replace("period = 0.01818181818181818", "period = 0.01818")  # stable text for the mutations
    bad = mutate(good)
    assert bad != good, "mutation did not apply"
    path = _write(tmp_path, bad)
    with pytest.raises(ModelFileError) as err:
        load_model(path)
    message = str(err.value)
    assert str(path) in message and f"'{key}'" in message and problem in message, message


KERNELS = [
    SquaredExponentialKernel(lengthscale=0.8),
    LocallyPeriodicKernel(sigma1=1.2, sigma2=0.495, period=1 / 55),
    ZeroMeanLocallyPeriodicKernel(sigma1=0.04, sigma2=4.8, period=1 / 55),
    PeriodicKernel(sigma2=0.7, period=0.02),
    SpindleKernel(sigma1=0.31, sigma2=0.37, per="tooth", teeth=3, spindle_rpm=2400.0),
]


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: k.kind)
def test_every_tracker_kernel_round_trips_as_its_struct(tmp_path, kernel):
    path = save_model(_model(tracker=TrackerConfig(kernel=kernel, gamma=7.5, budget=60)), tmp_path / "m.toml")
    text = path.read_text()
    table = text[text.index("[tracker]\n"):text.index("[identification]")]
    keys = [line.split(" = ")[0] for line in table.splitlines()[1:] if line]
    assert keys == ["kernel", *kernel.__struct_fields__, "gamma", "forgetting", "budget", "jitter", "search"]
    back = load_model(path).tracker
    assert type(back.kernel) is type(kernel) and back.kernel == kernel and back.kernel.kind == kernel.kind
    assert back.gamma == 7.5 and back.budget == 60
    assert back.build_kernel() == kernel.build()


def test_a_dict_is_no_tracker_kernel():
    with pytest.raises(TypeError, match="TrackerConfig.kernel must be one of"):
        TrackerConfig(kernel={"type": "locally_periodic", "sigma1": 1.2, "sigma2": 0.495, "period": 0.02})


def test_run_overrides_of_sigma_go_into_the_kernels_that_have_them():
    from monitor.online_settings import TrackerOverride, apply_overrides

    override = TrackerOverride(sigma1=0.5, sigma2=0.3, gamma=9.0)
    lp = _model()
    out = apply_overrides(lp, tracker=override)
    assert out.tracker.kernel == LocallyPeriodicKernel(sigma1=0.5, sigma2=0.3, period=1 / 55) and out.tracker.gamma == 9.0
    assert lp.tracker.kernel == KERNELS[1] and lp.tracker.gamma != 9.0  # the model itself unchanged
    se = apply_overrides(_model(tracker=TrackerConfig(kernel=KERNELS[0])), tracker=override)
    assert se.tracker.kernel == KERNELS[0] and se.tracker.gamma == 9.0  # σ1, σ2: not this kernel's
    periodic = apply_overrides(_model(tracker=TrackerConfig(kernel=KERNELS[3])), tracker=override)
    assert periodic.tracker.kernel == PeriodicKernel(sigma2=0.3, period=0.02)


@pytest.mark.parametrize("kernel, mutate, key, problem", [
    # a key of another kernel: the message says which keys the file's kernel takes
    (0, lambda t: t.replace("lengthscale = 0.8", "lengthscale = 0.8\nperiod = 0.02"), "tracker.period",
     "not a parameter of the squared_exponential kernel (it takes lengthscale)"),
    (1, lambda t: t.replace("period = 0.0181", "spindle_rpm = 3000.0\nperiod = 0.0181"), "tracker.spindle_rpm",
     "not a parameter of the locally_periodic kernel (it takes sigma1, sigma2, period)"),
    (3, lambda t: t.replace("sigma2 = 0.7", "sigma1 = 1.0\nsigma2 = 0.7"), "tracker.sigma1",
     "not a parameter of the periodic kernel (it takes sigma2, period)"),
    (4, lambda t: t.replace("teeth = 3", "teeth = 3\nperiod = 0.02"), "tracker.period",
     "not a parameter of the spindle kernel (it takes sigma1, sigma2, per, teeth, spindle_rpm)"),
    # a missing key: named with its range
    (0, lambda t: t.replace("lengthscale = 0.8", ""), "tracker.lengthscale",
     "missing; the squared_exponential kernel needs lengthscale (allowed: number ≥ 1e-06, ≤ 1e+06 s)"),
    (1, lambda t: t.replace("sigma2 = 0.495\n", ""), "tracker.sigma2",
     "missing; the locally_periodic kernel needs sigma1, sigma2, period (allowed: number ≥ 0.001, ≤ 1000)"),
    (4, lambda t: t.replace("spindle_rpm = 2400.0", ""), "tracker.spindle_rpm",
     "missing; the spindle kernel needs sigma1, sigma2, spindle_rpm (allowed: number > 0, ≤ 100000"),
    # a value out of the file's kernel's range: that kernel's range (σ1 of the spindle kernel ≤ 1e4 s)
    (4, lambda t: t.replace("sigma1 = 0.31", "sigma1 = 20000.0"), "tracker.sigma1", "(allowed: number ≥ 1e-06, ≤ 10000 s)"),
    (4, lambda t: t.replace('per = "tooth"', 'per = "flute"'), "tracker.per", "'revolution' / 'tooth'"),
    (4, lambda t: t.replace("teeth = 3", "teeth = 0"), "tracker.teeth", "≥ 1"),
    (0, lambda t: t.replace("[tracker]\nkernel = \"squared_exponential\"\n", "[tracker]\n"), "tracker.kernel", "missing"),
])
def test_a_tracker_table_of_the_wrong_shape_is_refused_naming_the_key(tmp_path, kernel, mutate, key, problem):
    good = save_model(_model(tracker=TrackerConfig(kernel=KERNELS[kernel])), tmp_path / "good.toml").read_text()
    good = good.replace("period = 0.01818181818181818", "period = 0.0181")
    bad = mutate(good)
    assert bad != good, "mutation did not apply"
    path = _write(tmp_path, bad)
    with pytest.raises(ModelFileError) as err:
        load_model(path)
    message = str(err.value)
    assert str(path) in message and f"'{key}'" in message and problem in message, message


@pytest.mark.parametrize("Ts, budget", [(1e-5, 2000), (1.0, 4), (1 / 333, 1500)])
def test_ranges_admit_real_drives(tmp_path, Ts, budget):
    beta = physical_to_beta("velocity-loop", Ts, 300.0, 300.0, gain=83300.0 * min(1.0, Ts * 333), coulomb=False)
    model = _model(Ts=Ts, beta=list(beta), beta_se=None, coulomb=False,
                   tracker=TrackerConfig(kernel=LocallyPeriodicKernel(sigma1=1.2, sigma2=0.495, period=max(2 * Ts, 1 / 55)),
                                         budget=budget))
    back = load_model(save_model(model, tmp_path / "m.toml"))
    assert back.Ts == Ts and back.tracker.budget == budget


def test_model_that_cannot_be_right_is_refused_on_load(tmp_path):
    # pole 1.004 ≥ 1 (velocity loop: p_d = β1 + β2)
    unstable = _model(beta=[0.8338, 0.1702, 1.02e-4, -1.03e-4], beta_se=None,
                      validity_warning="written with --force although invalid: pole")
    path = save_model(unstable, tmp_path / "forced.toml")
    assert "[validity]" in path.read_text()
    with pytest.raises(ModelFileError, match=r"forced.toml: key 'model.beta': the model cannot be right \(the file "
                                             r"was written with 'identify --force'\).*pole p_d = 1.004.*≥ 1"):
        load_model(path)
    assert load_model(path, allow_invalid=True).validity_warning.startswith("written with --force")
    negative = _model(beta=[0.8338, 0.1632, -1.02e-4, 1.03e-4], beta_se=None)
    with pytest.raises(ModelFileError, match=r"Coulomb friction negative beyond its uncertainty.*--method ls"):
        load_model(save_model(negative, tmp_path / "neg.toml"))


def test_not_toml_and_missing_file(tmp_path):
    with pytest.raises(ModelFileError, match="not a valid TOML"):
        load_model(_write(tmp_path, "\x00\x01 this is = = not toml"))
    with pytest.raises(ModelFileError, match="feedmon identify"):
        load_model(tmp_path / "absent.toml")


def test_non_finite_numbers_refused_when_saving(tmp_path):
    with pytest.raises(ValueError, match="finite"):
        save_model(_model(physical={"inertia": float("inf")}), tmp_path / "m.toml")
    with pytest.raises(ValueError, match="tracker.budget"):
        save_model(_model(tracker=TrackerConfig(budget=100000)), tmp_path / "m.toml")
    assert not (tmp_path / "m.toml").exists()


def test_docs_document_the_same_ranges():
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "model-file.md").read_text(encoding="utf-8")
    assert ranges_table() in doc, "docs/model-file.md's table is out of date: paste monitor.model_file.ranges_table()"


@pytest.mark.parametrize("edge", [
    {"sigma1": 1e-06, "period": 1e-06, "sigma2": 0.001, "jitter": 1e-08, "gamma": 0.0001, "budget": 2000},
    {"sigma1": 1e6, "period": 1e6, "sigma2": 1000.0, "jitter": 0.1, "gamma": 1e8, "forgetting": 0.5},
])
def test_the_range_limits_run_without_harm(simulated, tmp_path, edge):
    """Every value at the edge of its range runs through 'feedmon run --from' (no crash, no hang) and
    gives a finite estimate for every sample (a jitter of 0, once in range, gave NaN from the first
    division by γ² = 0 on)."""
    import re

    from feedio.mcapio import iter_blocks
    from feedmon.cli import main

    trial = simulated("shaker-constant", duration=2.0)
    path = tmp_path / "edge.toml"
    assert main(["identify", str(trial), "--period", str(1 / 55), "--no-tune", "-o", str(path)]) == 0
    text = path.read_text()
    for key, value in edge.items():
        text, count = re.subn(rf"(?m)^{key} = .*$", f"{key} = {float(value) if key != 'budget' else value}", text,
                              count=1)
        assert count == 1, key
    path.write_text(text)
    out = tmp_path / "est.mcap"
    assert main(["run", "--from", str(trial), "-o", str(out), "--model", str(path)]) == 0
    blocks = [b for _, b in iter_blocks(out, kinds=("disturbance",))]
    assert sum(len(b.t) for b in blocks) == int(round(2.0 * 333))
    f_next = np.array([v for b in blocks for v in b.f_next], dtype=float)
    assert np.all(np.isfinite(f_next))
