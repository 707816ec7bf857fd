"""The process monitors end to end: a simulated milling trial with a collision, a broken tooth and runout
put into its velocities (tests/process_edit.py), through ``feedmon run --from`` (alarms in the MCAP log) and
through the live monitor on a real Zenoh session (alarm message, status, MCAP sink)."""

from __future__ import annotations

import json
import math
import threading

import msgspec
import numpy as np
import pytest
from live_monitor import Live
from process_edit import add_force, tooth_share_force
from truth_models import make_trial

from feedio import schema as S
from feedio import transport as T
from feedio.mcapio import iter_blocks, read_trial
from feedmon.cli import main
from feedmon.run_config import load_config_file
from monitor.axes import load_axes
from monitor.model_file import save_model, truth_model
from monitor.process_monitor import MonitorSettings, build_monitors
from monitor.sinks.mcap_sink import McapProcessSink

K_EVENT = 2000  # the sample the events start at (6 s into a 12 s trial: a steady cut)
REV_PER_SAMPLE = 3000.0 / 60.0 / 333.0


@pytest.fixture(scope="module")
def mill(tmp_path_factory):
    """A 12 s slot-milling trial (nominal), its truth model, and copies with the events."""
    d = tmp_path_factory.mktemp("process")
    nom = make_trial(d / "nominal.mcap", 12.0, 3, "milling-incdec")
    tr = read_trial(nom)
    save_model(truth_model(tr.meta, period=1 / 100, budget=100), d / "m.model.toml")
    n, theta, force = tr.t.size, np.asarray(tr.spindle_angle), np.asarray(tr.truth.force)
    cut = float(force[K_EVENT - 500:K_EVENT].mean())
    impulse = np.zeros(n)
    impulse[K_EVENT:K_EVENT + 3] = 5.0 * cut  # a collision: 5× the cutting force for 3 samples
    context = {"program_line": np.where(np.arange(n) < 1000, 10, 11), "tool": np.full(n, 3)}
    add_force(nom, d / "collision.mcap", impulse, context=context)
    broken = np.zeros(n)
    broken[K_EVENT:] = tooth_share_force(theta[K_EVENT:], force[K_EVENT:], 1.0)  # tooth 0 cuts nothing
    add_force(nom, d / "broken.mcap", broken)
    runout = np.zeros(n)
    runout[K_EVENT:] = tooth_share_force(theta[K_EVENT:], force[K_EVENT:], -0.15)  # ±15 %: ΔA1 = 30 % of F
    add_force(nom, d / "runout.mcap", runout)
    return d


def _run(d, name: str, *extra: str) -> list[S.AlarmEvent]:
    out = d / f"{name}.out.mcap"
    assert main(["run", "--from", str(d / f"{name}.mcap"), "--model", str(d / "m.model.toml"), "-o", str(out),
                 "--monitors", *extra]) == 0
    return [b for _, b in iter_blocks(out, None, ("alarm",))]


def test_nominal_trial_raises_nothing(mill):
    assert _run(mill, "nominal") == []


def test_collision_within_three_samples_with_context(mill):
    (alarm,) = _run(mill, "collision")
    assert alarm.kind == "collision" and alarm.monitor == "impulse"
    # row j's force describes sample j − 1: rows K+1 … K+3 carry the impulse
    assert K_EVENT + 1 <= alarm.seq <= K_EVENT + 3
    assert alarm.value > alarm.limit >= 50.0 and alarm.sigma is not None and alarm.sigma > 0
    assert (alarm.program_line, alarm.tool) == (11, 3)


def test_broken_tooth_within_five_revolutions(mill):
    alarms = _run(mill, "broken")
    assert [a.kind for a in alarms] == ["broken_tooth"]
    assert 0 < (alarms[0].seq - K_EVENT) * REV_PER_SAMPLE <= 5.0


def test_runout_within_ten_revolutions(mill):
    alarms = _run(mill, "runout")
    assert [a.kind for a in alarms] == ["runout"]
    assert 0 < (alarms[0].seq - K_EVENT) * REV_PER_SAMPLE <= 10.0


def test_monitors_off_by_default_leave_the_log_unchanged(mill, tmp_path):
    out = tmp_path / "plain.mcap"
    assert main(["run", "--from", str(mill / "collision.mcap"), "--model", str(mill / "m.model.toml"),
                 "-o", str(out)]) == 0
    assert [b for _, b in iter_blocks(out, None, ("alarm",))] == []


def test_config_table_and_refusals(tmp_path):
    cfg = tmp_path / "run.toml"
    cfg.write_text('[monitors]\nenabled = true\n[monitors.impulse]\nlimit_N = 50.0\n'
                   '[monitors.envelope]\nreference = ["ref.json"]\n')
    ms = load_config_file(cfg).monitors
    assert ms.enabled and ms.impulse.limit_N == 50.0 and ms.envelope.reference == [str(tmp_path / "ref.json")]
    cfg.write_text("[monitors.tooth]\nteeth = 0\n")
    with pytest.raises(ValueError, match=r"monitors\.tooth\.teeth.*1 ≤ teeth ≤ 32"):
        load_config_file(cfg)


def test_live_alarm_on_zenoh_status_and_mcap(mill, tmp_path):
    axes = load_axes([str(mill / "m.model.toml")])
    trial = read_trial(mill / "collision.mcap")
    log = tmp_path / "live.mcap"
    sink = McapProcessSink(log, metas=[trial.meta], start_timeout=60)
    key = T.samples_key("feedmon-pm", "cnc-mill", "X")
    live = Live(axes, prefix="feedmon-pm", key=key, sinks=[sink],
                monitors=build_monitors(axes, MonitorSettings(enabled=True)))
    got: list[S.AlarmEvent] = []
    done = threading.Event()

    def on_alarm(sample):
        got.append(S.decode_alarm(sample.payload.to_bytes()))
        done.set()

    sub = live.s.declare_subscriber(T.alarm_key("feedmon-pm"), on_alarm)
    try:
        blocks = [b for _, b in iter_blocks(mill / "collision.mcap", None, ("samples",))]
        for b in blocks:
            for i in range(0, len(b.t), 10):  # blocks of 10 samples
                part = msgspec.structs.replace(
                    b, seq=b.seq + i, **{f: getattr(b, f)[i:i + 10] for f in S.SAMPLE_COLUMNS
                                        if getattr(b, f) is not None})
                live.pub.put(S.encode(part))
        assert done.wait(120.0)
        live.wait(lambda m: m.status()["axes"]["cnc-mill/X"]["process"]["alarms"] >= 1)
        st = live.monitor.status()["axes"]["cnc-mill/X"]["process"]
        assert st["by_kind"] == {"collision": 1} and st["last"]["seq"] == got[0].seq
        # an operator calls it a false alarm: the impulse monitor's limits widen
        live.s.put(T.ack_key("feedmon-pm", "cnc-mill", "X"), json.dumps({"monitor": "impulse"}))
        live.wait(lambda m: m.status()["axes"]["cnc-mill/X"]["process"]["widen"].get("impulse") == 1.5)
    finally:
        sub.undeclare()
        assert live.close() == []
    assert got[0].kind == "collision" and K_EVENT + 1 <= got[0].seq <= K_EVENT + 3
    logged = [b for _, b in iter_blocks(log, None, ("alarm",))]
    assert [(a.kind, a.seq) for a in logged] == [(got[0].kind, got[0].seq)]
    assert math.isfinite(logged[0].t)


def test_bridge_feed_hold_pin_follows_a_process_alarm_until_acknowledged():
    """The LinuxCNC bridge's way back (without HAL): a process alarm raises the axis' ``alarm`` pin (wired to
    feed hold); the operator's acknowledgement (``feedmon alarm ack``) clears it."""
    import time

    from bridge.linuxcnc import wayback as W
    from bridge.linuxcnc.config import AxisConfig, BridgeConfig
    from monitor.sinks.rerun_events import alarm_line

    cfg = BridgeConfig(machine="m", servo_period=0.001, counter="c", columns=["c", "v", "x"],
                       axes={"X": AxisConfig(v_ref="v", position="x", length_scale=0.001)}).check()
    sent: list[dict] = []
    wb = W.WayBack(cfg, "pm", lambda values: sent.append(values) or True)
    port = T.free_tcp_port()
    a = T.open_session(listen=f"tcp/127.0.0.1:{port}")
    b = T.open_session(connect=f"tcp/127.0.0.1:{port}")
    try:
        wb.subscribe(b)
        pub = a.declare_publisher(T.alarm_key("pm", "m", "X"))
        assert T.wait_for_matching(pub, 10)
        ev = S.AlarmEvent(machine="m", axis="X", seq=7, t=0.5, kind="collision", monitor="impulse", value=300.0,
                          limit=150.0, sigma=2.0, tool=3)
        pub.put(S.encode(ev))
        deadline = time.monotonic() + 10
        while not wb.current()["X.alarm"]:
            assert time.monotonic() < deadline, "the process alarm reaches the pin"
            time.sleep(0.01)
        assert {"X.alarm": True} in sent
        assert main(["alarm", "ack", "m/X", "--monitor", "impulse", "--prefix", "pm",
                     "--connect", f"tcp/127.0.0.1:{port}"]) == 0
        while wb.current()["X.alarm"]:
            assert time.monotonic() < deadline + 10, "the acknowledgement clears the pin"
            time.sleep(0.01)
        assert wb.alarm_state("X") == {"process": False}
    finally:
        wb.close()
        b.close()
        a.close()
    line = alarm_line(ev)
    assert line.startswith("ALARM collision at t = 0.500 s: 300.0 against limit 150.0 N, σ 2.00 N, tool 3")
