"""The process monitors on the Rerun dashboard: a live monitor (real Zenoh session, the Rerun recording process)
with the monitors on, fed a simulated milling trial whose tooth 1 breaks; the real .rrd read back with Rerun's
dataframe API has the per-tooth panel, the monitors' limits on the force panel and the alarm's marker."""

from __future__ import annotations

import math
import threading

import msgspec
import numpy as np
import pytest
from live_monitor import Live
from test_dashboard import open_rrd, rrd_rows, rrd_scalars, tensor

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import iter_blocks, read_trial
from feedmon.cli import main
from monitor.axes import load_axes
from monitor.model_file import save_model, truth_model
from monitor.process_monitor import MonitorSettings, build_monitors
from monitor.sinks.rerun_layout import AxisView, axis_blueprint
from monitor.sinks.rerun_process import RerunProcessSink

BREAK_S = 3.0  # tooth 1 breaks (the scenario's 9 s, earlier: a 4 s trial)


@pytest.fixture(scope="module")
def trial(tmp_path_factory):
    d = tmp_path_factory.mktemp("dash_process")
    cfg = d / "break.toml"
    cfg.write_text(f"[process]\nbreaks = [[1, {BREAK_S}, 0.001]]\n")
    path = d / "tooth-break.mcap"
    assert main(["simulate", "milling-tooth-break", "-o", str(path), "--seed", "2", "--duration", "4",
                 "--config", str(cfg)]) == 0
    save_model(truth_model(read_trial(path).meta, period=1 / 50, budget=100), d / "m.model.toml")
    return d, path


def _replay(live: Live, path, n: int = 10) -> None:
    """The trial's sample blocks, cut into blocks of ``n`` samples, on the monitor's key."""
    for _, b in iter_blocks(path, None, ("samples",)):
        for i in range(0, len(b.t), n):
            live.pub.put(S.encode(msgspec.structs.replace(
                b, seq=b.seq + i, **{f: getattr(b, f)[i:i + n] for f in S.SAMPLE_COLUMNS
                                    if getattr(b, f) is not None})))


def test_per_tooth_panel_limits_and_alarm_marker_in_a_live_recording(trial, tmp_path):
    d, path = trial
    axes = load_axes([str(d / "m.model.toml")])
    rrd = tmp_path / "process.rrd"
    sink = RerunProcessSink(rrd, batch_interval=0.05, start_timeout=60)
    ms = MonitorSettings(enabled=True)
    live = Live(axes, prefix="feedmon-dp", key=T.samples_key("feedmon-dp", "cnc-mill", "X"), sinks=[sink],
                monitors=build_monitors(axes, ms))
    got: list[S.AlarmEvent] = []
    done = threading.Event()
    sub = live.s.declare_subscriber(T.alarm_key("feedmon-dp"), lambda s: (got.append(S.decode_alarm(
        s.payload.to_bytes())), done.set()))
    n = read_trial(path).t.size
    try:
        _replay(live, path)
        assert done.wait(120.0)
        live.wait(lambda m: m.status()["axes"]["cnc-mill/X"]["last_seq"] == n - 1)
    finally:
        sub.undeclare()
        assert live.close() == []
    assert sink.status()["failures"] == 0, sink.status()["last_error"]
    (alarm,) = got
    assert alarm.kind == "broken_tooth" and alarm.t > BREAK_S
    store = open_rrd(rrd)
    # the per-tooth panel: the last revolution over 36 angle bins (°), a bar per tooth (2 teeth)
    s_prof, t_prof, prof = rrd_rows(store, "/cnc-mill/X/tooth/profile", "BarChart:values")
    _, _, absc = rrd_rows(store, "/cnc-mill/X/tooth/profile", "BarChart:abscissa")
    _, _, peaks = rrd_rows(store, "/cnc-mill/X/tooth/peaks", "BarChart:values")
    # (a bin no sample fell in has no bar: 333 Hz against 3000 rpm is 20 angles a revolution, repeated)
    centres = (np.arange(ms.tooth.bins) + 0.5) * 360.0 / ms.tooth.bins
    assert len(prof) > 50 and all(len(tensor(p)) == len(tensor(a)) <= ms.tooth.bins for p, a in zip(prof, absc))
    assert all(np.isin(tensor(a), centres).all() for a in absc)
    assert np.mean([len(tensor(p)) for p in prof[20:]]) >= 18 and all(np.isfinite(tensor(p)).all() for p in prof)
    assert all(len(tensor(p)) == ms.tooth.teeth and np.isfinite(tensor(p)).all() for p in peaks)
    # a revolution is ~6.7 samples at 3000 rpm and 333 Hz: one chart a view
    assert np.all(np.diff(s_prof) > 0) and s_prof[-1] > (n - 100)
    before = [tensor(p) for s, p in zip(s_prof, peaks) if 2.0 < s * S_TS < BREAK_S]
    after = [tensor(p) for s, p in zip(s_prof, peaks) if s * S_TS > BREAK_S + 0.3]
    assert before and after
    # before the break both teeth cut alike; after it one tooth cuts the chip of both
    ratio = lambda ps: max(ps) / max(min(ps), 1e-9)  # noqa: E731
    assert np.median([ratio(p) for p in before]) < 1.5 < np.median([ratio(p) for p in after])
    # A1 against the tooth monitor's limit: below before the break, above at the alarm
    s_a1, _, a1 = rrd_scalars(store, "/cnc-mill/X/tooth/a1")
    s_lim, _, lim = rrd_scalars(store, "/cnc-mill/X/tooth/a1_broken")
    assert lim.size and np.isfinite(lim).all()
    common, ia, ib = np.intersect1d(s_a1, s_lim, return_indices=True)
    early = common * S_TS < BREAK_S
    assert early.any() and np.all(a1[ia][early] < lim[ib][early])
    assert np.any(a1[ia][~early] > lim[ib][~early])
    # the collision range on the force panel: finite, about the force, low < high
    s_hi, _, hi = rrd_scalars(store, "/cnc-mill/X/force/limit/collision_high")
    s_lo, _, lo = rrd_scalars(store, "/cnc-mill/X/force/limit/collision_low")
    assert hi.size > 50 and np.array_equal(s_hi, s_lo) and np.all(hi - lo >= 2 * ms.impulse.limit_N)
    assert np.all(np.diff(s_hi) * S_TS >= 0.02 - 1e-9)  # at most one view per 20 ms of data
    assert rrd_scalars(store, "/cnc-mill/X/force/limit/band_high")[0].size == 0  # no reference: no band
    # the alarm's marker: at the alarm's row and time, on the filtered estimate there
    s_m, t_m, y_m = rrd_scalars(store, "/cnc-mill/X/force/marker/broken_tooth")
    assert s_m.tolist() == [alarm.seq] and abs(t_m[0] - alarm.t) < 2e-9
    s_e, _, est = rrd_scalars(store, "/cnc-mill/X/force/estimate")
    assert math.isclose(y_m[0], est[s_e == alarm.seq - 1][0])


S_TS = 1.0 / 333.0


def test_the_per_tooth_row_is_there_only_with_the_monitors():
    """Without process monitors the axis' blueprint is what it was; with them one row more."""
    plain = AxisView("/m/X", "m", "X", True, False)
    assert plain == AxisView("/m/X", "m", "X", True, False, False)
    rows = len(axis_blueprint(plain).contents)
    assert len(axis_blueprint(AxisView("/m/X", "m", "X", True, False, True)).contents) == rows + 1
