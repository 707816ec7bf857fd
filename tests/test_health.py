"""Health statistics (kernels.health): false alarms on white noise, detection, hysteresis, persistence."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kernels.health import HEALTH_RANGES, PARAMS, HealthConfig, HealthMonitor

TS = 1 / 333
THETA = {"inertia": 300.0, "damping": 300.0, "coulomb_pos": 9.0, "coulomb_neg": 10.0}
SE_FILE = {"inertia": 1.0, "damping": 3.0, "coulomb_pos": 0.2, "coulomb_neg": 0.2}
SE_PRIOR = {"inertia": 90.0, "damping": 90.0, "coulomb_pos": 3.0, "coulomb_neg": 3.0}


def _monitor(**cfg):
    return HealthMonitor(TS, THETA, SE_FILE, SE_PRIOR, config=HealthConfig(**cfg))


def test_white_noise_of_unit_variance_never_warns():
    """2 million N(0, 1) innovations (~1.7 h at 333 Hz): the innovation level stays ok."""
    hm = _monitor(warmup=0.0)
    rng = np.random.default_rng(0)
    for _ in range(4):
        levels = hm.learn_many(rng.standard_normal(500_000))
        assert levels.max() == 0
    v = hm.verdict()
    assert v.state == "ok" and v.reasons == [] and 0.9 < v.nu2_mean < 1.1


def test_heavy_tailed_nominal_bursts_do_not_warn():
    """Isolated bursts (|ν| up to 30 for 20 samples, as at an abrupt disturbance onset) are clipped
    and shorter than the persistence: no warning."""
    hm = _monitor(warmup=0.0)
    rng = np.random.default_rng(1)
    nu = rng.standard_normal(333 * 120)
    for k in range(1000, nu.size, 333 * 6):
        nu[k:k + 20] = 30.0 * rng.choice([-1, 1], 20)
    assert hm.learn_many(nu).max() == 0


def test_variance_step_is_detected_within_the_persistence():
    """ν s.d. 1 → 3 (variance ×9, clipped mean ≈ 6.3): warn within 1 s (EWMA rise ~0.7 s + 0.25 s
    persistence); s.d. 8 (clipped mean ≈ 12): alarm within 1 s; back to ok after the change ended."""
    hm = _monitor(warmup=0.0)
    rng = np.random.default_rng(2)
    k0 = 333 * 20
    nu = rng.standard_normal(333 * 40)
    nu[k0:k0 + 333 * 5] *= 3.0
    levels = hm.learn_many(nu)
    assert levels[:k0].max() == 0
    first_warn = k0 + int(np.argmax(levels[k0:] >= 1))
    assert levels[first_warn] == 1 and 0.25 <= (first_warn - k0) * TS < 1.0
    assert levels[k0 + 333 * 5 + 333 * 10] == 0          # cleared after the change ended (+ hold)
    hm2 = _monitor(warmup=0.0)
    nu2 = rng.standard_normal(333 * 30)
    nu2[k0:] *= 8.0
    lv2 = hm2.learn_many(nu2)
    first_alarm = k0 + int(np.argmax(lv2[k0:] == 2))
    assert lv2[first_alarm] == 2 and (first_alarm - k0) * TS < 1.0


def test_unexplained_periodic_disturbance_is_a_model_error():
    """A sinusoid the model does not explain (a spindle change without spindle data) in the innovations."""
    hm = _monitor(warmup=0.0)
    rng = np.random.default_rng(3)
    t = np.arange(333 * 30) * TS
    nu = rng.standard_normal(t.size) + np.where(t >= 15.0, 4.0 * np.sin(2 * np.pi * 40.0 * t), 0.0)
    levels = hm.learn_many(nu)
    k0 = int(15.0 / TS)
    assert levels[:k0].max() == 0
    assert (int(np.argmax(levels[k0:] >= 1))) * TS < 1.0
    v = hm.verdict()
    assert v.state in ("warn", "alarm") and any("innovation" in r for r in v.reasons)


def test_level_sitting_at_the_threshold_does_not_flap():
    """EWMA hovering around θ_warn: once warned it stays warned (clears only below θ_clear)."""
    hm = _monitor(warmup=0.0)
    rng = np.random.default_rng(4)
    nu = rng.standard_normal(333 * 60) * math.sqrt(5.2)   # E[ν²] ≈ 5.2 (clipped a little): at θ_warn = 5
    levels = hm.learn_many(nu)
    changes = int(np.count_nonzero(np.diff(levels)))
    assert changes <= 2, changes


def test_parameter_drift_warn_alarm_and_hysteresis():
    hm = _monitor()
    th = dict(THETA)
    se = {"inertia": 2.0, "damping": 5.0, "coulomb_pos": 0.3, "coulomb_neg": 0.3}
    assert hm.verdict(th, se).state == "ok"
    th["inertia"] = 330.0                                  # +10 %, 13 s.e.: warn (alarm needs 15 %)
    v = hm.verdict(th, se)
    assert v.levels["inertia"] == "warn" and v.state == "warn" and "inertia drift +10.0 %" in v.reasons[0]
    th["inertia"] = 360.0                                  # +20 %, 27 s.e.
    assert hm.verdict(th, se).levels["inertia"] == "alarm"
    # a parameter moving around the warn threshold: z between z_clear and z_warn keeps the warn
    hm2 = _monitor()
    states = []
    cfg = hm2.config
    for z in (cfg.z_warn + 0.2, cfg.z_warn - 0.1, cfg.z_warn + 0.1, cfg.z_clear + 0.5, cfg.z_clear + 0.3,
              cfg.z_warn + 0.05, cfg.z_clear + 0.1):
        th2 = dict(THETA, damping=300.0 + z * math.hypot(5.0, 3.0))
        states.append(hm2.verdict(th2, se).levels["damping"])
    assert states == ["warn"] * 7
    th2 = dict(THETA, damping=300.0 + (cfg.z_clear - 0.5) * math.hypot(5.0, 3.0))
    assert hm2.verdict(th2, se).levels["damping"] == "ok"  # below z_clear


def test_parameter_the_data_do_not_determine_never_warns():
    hm = _monitor()
    th = dict(THETA, damping=1500.0)                       # +400 % …
    se = {"inertia": 2.0, "damping": 80.0, "coulomb_pos": 0.3, "coulomb_neg": 0.3}   # … but s.e. ≈ prior
    v = hm.verdict(th, se)
    assert v.levels["damping"] == "ok" and not v.determined["damping"]
    assert v.determined["inertia"]


def test_practically_irrelevant_drift_does_not_warn():
    hm = HealthMonitor(TS, THETA, dict(SE_FILE, inertia=0.1), SE_PRIOR)
    th = dict(THETA, inertia=303.0)                        # +1 % at 30 standard errors
    se = {"inertia": 0.1, "damping": 5.0, "coulomb_pos": 0.3, "coulomb_neg": 0.3}
    v = hm.verdict(th, se)
    assert abs(v.z["inertia"]) > 10 and v.levels["inertia"] == "ok"


def test_settings_out_of_range_are_refused_by_name():
    with pytest.raises(ValueError, match="tau"):
        HealthConfig(tau=0.0).validate()
    with pytest.raises(ValueError, match="clear"):
        HealthConfig(clear=6.0).validate()
    with pytest.raises(ValueError, match="kappa"):
        HealthConfig(kappa=1.5).validate()
    with pytest.raises(ValueError, match="warmup"):
        HealthConfig(warmup=float("nan")).validate()
    with pytest.raises(ValueError, match="entries"):
        HealthMonitor(TS, [1.0, 2.0])


def test_the_model_file_and_the_kernel_check_the_same_ranges():
    """One range per setting (HEALTH_RANGES): the ``[health]`` Struct declares it, HealthConfig checks it;
    just beyond either end both refuse, naming the setting."""
    import dataclasses

    import msgspec

    from feedio.limits import field_range
    from monitor.online_settings import Health

    assert set(HEALTH_RANGES) == {f.name for f in dataclasses.fields(HealthConfig)}
    for name, (lo, hi, open_low, _) in HEALTH_RANGES.items():
        assert field_range(Health, name) == (lo, hi)
        for bad in (hi + 1e-9 * max(1.0, hi), lo if open_low else lo - 1e-9):
            with pytest.raises(ValueError, match=name):
                dataclasses.replace(HealthConfig(), **{name: bad}).validate()
            with pytest.raises(msgspec.ValidationError, match=name):
                msgspec.convert({name: bad}, Health)


def test_snapshot_restore_round_trip():
    rng = np.random.default_rng(5)
    a = _monitor(warmup=0.0)
    nu = rng.standard_normal(5000) * 2.5
    a.learn_many(nu[:2500])
    snap = a.snapshot()
    b = _monitor(warmup=0.0)
    b.restore(snap)
    np.testing.assert_array_equal(a.learn_many(nu[2500:]), b.learn_many(nu[2500:]))
    for k in snap:
        assert isinstance(snap[k], np.ndarray)
    snap["health.acc"] = np.zeros(2)
    with pytest.raises(ValueError, match="health.acc"):
        b.restore(snap)


def test_all_params_have_reference_slots():
    hm = _monitor()
    v = hm.verdict()
    assert set(v.levels) == {"innovation", *PARAMS}
    assert math.isnan(v.z["offset"])                      # no offset in this model: never tested
