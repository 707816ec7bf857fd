"""Health covers the input itself (:mod:`monitor.input_health`), through the real path: a ``feedmon run``
subprocess fed over real Zenoh, ``feedmon status`` asked as a user would, ``run --from`` offline. A frozen
``v_meas`` while the axis moves (a dead encoder), a stream at another rate than the model, an axis that
learns nothing: each turns the health to warn/alarm with the reason, estimation goes on, and a tracker
state learned from a stream the monitor flagged is not saved over the good one."""

from __future__ import annotations

import re
import subprocess
import sys

import msgspec
import numpy as np
import pytest
import zenoh
from test_bad_input import AXIS, PREFIX, MonitorProc, blocks_of, wait_status
from truth_models import truth_workdir

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import TrialWriter, iter_file, read_trial
from feedmon.cli import main
from kernels import online
from monitor.input_health import InputHealth, InputHealthSettings


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return truth_workdir(tmp_path_factory, "input_health", duration=8.0, seed=6)


@pytest.fixture(scope="module")
def trial(work):
    return read_trial(work / "trial.mcap")


def _frozen(trial, start: int = 300) -> list[S.SampleBlock]:
    """The trial with v_meas stuck at its value of sample ``start`` from then on (a dead encoder)."""
    out = []
    for b in blocks_of(trial, 0, len(trial), 10):
        if b.seq + 10 > start:
            b = msgspec.structs.replace(b, v_meas=[x if b.seq + i < start else float(trial.v_meas[start])
                                                   for i, x in enumerate(b.v_meas)])
        out.append(b)
    return out


def _publish(mon: MonitorProc, trial, blocks: list[S.SampleBlock], pred) -> dict:
    with T.open_session(connect=mon.endpoint) as s:
        pub = s.declare_publisher(T.samples_key(PREFIX, trial.machine, trial.axis),
                                  congestion_control=zenoh.CongestionControl.BLOCK)
        assert T.wait_for_matching(pub, 15.0)
        for b in blocks:
            pub.put(S.encode(b))
        return wait_status(s, pid=mon.proc.pid, pred=pred, timeout=60)


def _input_reasons(h: dict) -> list[str]:
    return [r for r in h.get("reasons") or [] if r.startswith("input:")]


def test_a_frozen_measurement_while_moving_raises_an_alarm_live_and_offline(work, trial, tmp_path):
    n = len(trial)
    blocks = _frozen(trial)
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--fresh", "--state-dir",
                                                     str(tmp_path / "st"), "--mcap", str(tmp_path / "log.mcap")])
    try:
        st = _publish(mon, trial, blocks, lambda x: x["axes"][AXIS]["estimates_out"] == n)
        a = st["axes"][AXIS]
        assert a["stale"] > n / 2 and a["dropped_total"] == 0  # estimation went on
        assert a["health"]["state"] == "alarm" and a["input"]["state"] == "alarm", a["health"]
        assert "v_meas frozen while the axis moves" in _input_reasons(a["health"])[0]
        shown = subprocess.run([sys.executable, "-m", "feedmon.cli", "status", "--connect", mon.endpoint, "--prefix",
                                PREFIX], capture_output=True, text=True, timeout=60)
        assert shown.returncode == 0 and "v_meas frozen" in shown.stdout and "alarm" in shown.stdout, shown.stdout
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    assert "health ok → warn" in mon.stderr and "warn → alarm" in mon.stderr  # said once each, in the log
    live = [h for _, _, _, h in iter_file(tmp_path / "log.mcap", [AXIS], kinds=("health",))]
    assert live[-1].state == "alarm" and "v_meas frozen" in live[-1].reasons[0]
    # offline, the same stream gives the same verdict at the same samples
    src = tmp_path / "frozen.mcap"
    with TrialWriter(src, trial.meta, start="2024-05-01T08:00:00Z") as w:
        for b in blocks:
            w.write_samples(b)
    assert main(["run", "--from", str(src), "-o", str(tmp_path / "est.mcap"), "--model", str(work / "z.model.toml")]) == 0
    off = [h for _, _, _, h in iter_file(tmp_path / "est.mcap", [AXIS], kinds=("health",))]
    assert [(h.seq, h.state, h.reasons[:1]) for h in off] == [(h.seq, h.state, h.reasons[:1]) for h in live]


def test_a_stream_at_another_rate_is_flagged_and_its_state_not_saved_over_the_good_one(work, trial, tmp_path):
    """1 kHz time stamps into a model of 333 Hz: alarm with the reason, in the status and the table; the
    tracker state learned from it does not replace the one a good stream left."""
    n = len(trial)
    state = tmp_path / "st"
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--state-dir", str(state)])
    try:
        _publish(mon, trial, blocks_of(trial, 0, n, 10), lambda x: x["axes"][AXIS]["estimates_out"] == n)
    finally:
        assert mon.stop() == 0, mon.stderr
    good = state / "linear-drive+Z.state.npz"
    before = good.read_bytes()
    fast = [msgspec.structs.replace(b, t=[x * 0.333 for x in b.t]) for b in blocks_of(trial, 0, n, 10)]
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--state-dir", str(state)])
    try:
        assert "tracker state restored" in mon.stderr
        st = _publish(mon, trial, fast, lambda x: x["axes"][AXIS]["estimates_out"] == n)
        a = st["axes"][AXIS]
        assert a["counters"]["interval_mismatch"] >= n - 2 and a["dropped_total"] == 0
        assert a["health"]["state"] == "alarm" and a["input"]["tainted"] > 0
        assert "at another interval than the model's Ts = 3.003 ms (recent median 1 ms)" in \
            _input_reasons(a["health"])[0], a["health"]
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    assert "tracker state of linear-drive/Z NOT saved" in mon.stderr and "tracker state saved" not in mon.stderr
    assert good.read_bytes() == before  # the good state is kept


def test_an_axis_that_learns_nothing_for_long_is_flagged(work, trial, tmp_path):
    """Every sample refused (an absurd velocity): the tracker's loop makes no health report at all, yet the
    verdict says nothing was learned, warn then alarm, at the thresholds of [run.input_health]."""
    cfg = tmp_path / "run.toml"
    cfg.write_text("[run.input_health]\nlearn_warn = 1.0\nlearn_alarm = 2.0\n")
    n = 1000
    bad = [msgspec.structs.replace(b, v_meas=[100.0] * len(b.t)) for b in blocks_of(trial, 0, n, 10)]
    mon = MonitorProc(prefix=PREFIX, cwd=work, args=["--model", "z.model.toml", "--fresh", "--state-dir",
                                                     str(tmp_path / "st"), "--config", str(cfg)])
    try:
        st = _publish(mon, trial, bad, lambda x: x["axes"][AXIS]["samples_in"] == n)
        a = st["axes"][AXIS]
        assert a["trained"] == 0 and a["counters"]["rejected_out_of_range"] == n
        assert a["health"]["state"] == "alarm" and a["health"]["changes"] == 2, a["health"]  # ok → warn → alarm
        assert re.fullmatch(r"input: nothing learned from the last (\d+) samples \([0-9.]+ s\): all stale, rejected "
                            r"or refused — see the axis' counters", _input_reasons(a["health"])[0]), a["health"]
        assert int(_input_reasons(a["health"])[0].split()[6]) > n - 400  # reported again about once a second
    finally:
        assert mon.stop() == 0, mon.stderr
    assert "health ok → warn" in mon.stderr


# ---- the verdict itself ------------------------------------------------------------------------------------
def _counts(n: int, stale: int = 0, interval: int = 0, trained: int | None = None) -> np.ndarray:
    c = np.zeros(len(online.COUNTERS), dtype=np.int64)
    c[online.COUNTERS.index("stale")] = stale
    c[online.COUNTERS.index("interval_mismatch")] = interval
    c[online.COUNTERS.index("trained")] = n - stale if trained is None else trained
    return c


def test_the_verdict_judges_fractions_over_the_window_with_hysteresis():
    """Window 10 s at Ts = 10 ms: the last 1000 samples, in buckets of 100; samples learned while flagged
    are counted (tainted)."""
    ih = InputHealth(0.01, InputHealthSettings(window=10.0))

    def feed(blocks: int, n: int, **kw) -> None:
        for _ in range(blocks):
            ih.block(_counts(n, **kw), n)

    feed(10, 100, stale=10)  # 10 % stale
    assert ih.state == "ok" and ih.tainted == 0
    feed(3, 100, stale=100)  # 370 of the last 1000
    assert ih.state == "warn" and ih.levels == {"stale": 1, "interval": 0, "learn": 0} and ih.tainted == 0
    feed(1, 1000, stale=900)  # one long block: 90 %
    assert ih.state == "alarm" and ih.tainted == 100
    feed(10, 100, stale=15)  # 15 %: below warn (20 %), not below half of it: stays warn
    assert ih.state == "warn" and ih.tainted == 100 + 10 * 85
    feed(10, 100, stale=5)  # 14, 13, 12, 11, 10 % still warn, then 9 % and below: ok
    assert ih.state == "ok" and ih.reasons == [] and ih.tainted == 950 + 5 * 95
    feed(4, 100, interval=100)
    assert ih.levels["interval"] == 1 and "another interval" in ih.reasons[0]
    feed(1, 100, interval=100)  # 500 of 1000
    assert ih.levels["interval"] == 2 and ih.tainted == 1425 + 500


def test_input_health_settings_are_checked():
    with pytest.raises(msgspec.ValidationError, match="window"):
        msgspec.convert({"window": 0.1}, InputHealthSettings)
    with pytest.raises(ValueError, match="stale_warn .* must not exceed input_health.stale_alarm"):
        InputHealthSettings(stale_warn=0.9, stale_alarm=0.5)
