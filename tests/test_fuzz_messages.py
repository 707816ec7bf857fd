"""Fuzzing the message path: random, mutated and junk messages through the real decode → key check →
route → estimate path of a started :class:`Monitor` (real Zenoh session), and a seeded batch through
real Zenoh to a real ``feedmon run``.

Properties, for every message:

* nothing raises (the daemon never dies of a message) and no internal error is counted;
* exactly one outcome is counted: ``malformed``, ``key_mismatch``, no model, or routed to the axis;
* a routed block is within the documented contract (names, ``seq``, ``t`` bounds) and equal to the
  message as plain ``json.loads`` reads it (accepted data unchanged), and its estimate is bit for bit
  that of a reference estimator fed exactly the routed blocks (same code path, same process), so
  the tracker is never touched by a refused message;
* a message built valid (not mutated, on its own key) is never refused.

Bounded time: a fixed number of derandomized examples, small blocks.
"""

from __future__ import annotations

import json
import math
import random
import time

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from monitor_proc import MonitorProc
from test_bad_input import PREFIX, wait_status
from truth_models import model_from_truth

from feedio import schema as S
from feedio import transport as T
from feedio.limits import NAME_RE, SEQ_MAX, T_MAX
from monitor.axes import load_axes
from monitor.daemon import Monitor
from monitor.estimator import AxisEstimator
from monitor.warm import warm_up
from replay.scenarios import load_scenario
from replay.simulator import simulate, write_trial

MACHINE, AXIS_NAME = "linear-drive", "Z"
COLUMNS = ("v_ref", "v_meas", "u", "current", "position", "spindle_rpm")
EDGE_SEQ = [-1, 0, 1, SEQ_MAX - 3, SEQ_MAX, SEQ_MAX + 1, 2**63 - 1, 2**63, 2**64, 10**30, True, 1.0, "7", None]
EDGE_T = [-0.0, 0.0, 5e-324, T_MAX, T_MAX * (1 + 1e-15), 2e10, 1e308, -1e-300, math.inf, -math.inf, math.nan,
          10**400, True, "1.0", None, [0.1]]
EDGE_NAMES = ["", "a" * 64, "a" * 65, "[/]", "a\n", "a\r\nb", "-x", ".x", "x\x1b[31m", "ä", "a b", "a/b", "*", 7,
              None, ["x"], "ghost", MACHINE, AXIS_NAME]
EDGE_VALUES = [None, True, 0, -1, 2**64, 10**400, 1e308, -1e308, math.inf, math.nan, "", "x" * 1000, [], {},
               [[[]]], {"a": {"b": [1, None]}}, "\x00\r\n\x1b"]


# ---- generation, shared by hypothesis and a seeded random generator -------------------------------
class _Random:
    def __init__(self, seed: int) -> None:
        self.r = random.Random(seed)

    def pick(self, xs):
        return xs[self.r.randrange(len(xs))]

    def integer(self, lo: int, hi: int) -> int:
        return self.r.randint(lo, hi)

    def real(self, lo: float, hi: float) -> float:
        return self.r.uniform(lo, hi)

    def raw(self, n: int) -> bytes:
        return bytes(self.r.randrange(256) for _ in range(n))


class _Draw(_Random):
    def __init__(self, data) -> None:
        self.d = data

    def pick(self, xs):
        return self.d.draw(st.sampled_from(xs))

    def integer(self, lo: int, hi: int) -> int:
        return self.d.draw(st.integers(lo, hi))

    def real(self, lo: float, hi: float) -> float:
        return self.d.draw(st.floats(lo, hi, allow_nan=False))

    def raw(self, n: int) -> bytes:
        return self.d.draw(st.binary(min_size=0, max_size=n))


def _valid(c, seq: int, t0: float) -> dict:
    n = c.integer(1, 12)
    machine, axis = c.pick([(MACHINE, AXIS_NAME)] * 4 + [("ghost", "Q"), ("linear-drive", "Y")])
    d = {"machine": machine, "axis": axis, "seq": seq, "t": [t0 + 0.003 * i for i in range(n)],
         "v_ref": [c.real(-0.2, 0.2) for _ in range(n)], "v_meas": [c.real(-0.2, 0.2) for _ in range(n)]}
    for col in COLUMNS[2:]:
        if c.integer(0, 5) == 0:
            d[col] = [c.real(-100.0, 100.0) for _ in range(n)]
    if c.integer(0, 6) == 0:  # a missing reading
        d["v_meas"][c.integer(0, n - 1)] = None
    return d


def _mutate(c, d: dict) -> dict | bytes:
    op = c.integer(0, 11)
    d = json.loads(json.dumps(d))
    fields = list(d)
    if op == 0:
        d[c.pick(fields)] = c.pick(EDGE_VALUES)
    elif op == 1:
        del d[c.pick(fields)]
    elif op == 2:
        d[c.pick(["curent", "v_ref ", "", "\r\nx", "seq2", "t" * 70])] = c.pick(EDGE_VALUES)
    elif op == 3:
        d["seq"] = c.pick(EDGE_SEQ)
    elif op == 4:
        d["t"][c.integer(0, len(d["t"]) - 1)] = c.pick(EDGE_T)
    elif op == 5:
        d[c.pick(["machine", "axis"])] = c.pick(EDGE_NAMES)
    elif op == 6:
        col = c.pick([k for k in fields if k in COLUMNS or k == "t"])
        d[col] = d[col][:-1] if c.integer(0, 1) else d[col] + [0.0]
    elif op == 7:
        col = c.pick([k for k in fields if k in COLUMNS])
        d[col][0] = c.pick([math.inf, -math.inf, math.nan, 1e308, 2**64, 10**400, "fast", [1.0], {}])
    elif op == 8:  # nested junk
        depth = c.pick([10, 1000, 50_000])
        return json.dumps(d).encode()[:-1] + b', "u": ' + b"[" * depth + b"]" * depth + b"}"
    elif op == 9:  # truncated
        raw = json.dumps(d).encode()
        return raw[:c.integer(0, len(raw) - 1)]
    elif op == 10:  # one byte changed
        raw = bytearray(json.dumps(d).encode())
        raw[c.integer(0, len(raw) - 1)] = c.integer(0, 255)
        return bytes(raw)
    else:
        return c.pick([b"", b"null", b"[]", b"{}", b'"x"', b"\xff\xfe", b"{" * 100]) + c.raw(40)
    return d


def _encode(d) -> bytes:
    return d if isinstance(d, bytes) else json.dumps(d).encode()  # NaN/Infinity tokens stay in: invalid JSON


def _key_for(c, d, mutated: bool) -> str:
    if isinstance(d, dict) and isinstance(d.get("machine"), str) and isinstance(d.get("axis"), str) and \
            NAME_RE.fullmatch(d["machine"]) and NAME_RE.fullmatch(d["axis"]) and not (mutated and c.integer(0, 3) == 0):
        return T.samples_key(PREFIX, d["machine"], d["axis"])
    m, a = c.pick([(MACHINE, AXIS_NAME), ("other-machine", "Y"), ("ghost", "Q"), ("k" * 300, "x\r\ny")])
    return f"{PREFIX}/{m}/{a}/samples"


def messages(c, count: int, seq0: int = 0) -> list[tuple[str, bytes, bool]]:
    """``(key, payload, built_valid)`` of ``count`` messages, a third of them valid."""
    out, seq, t0 = [], seq0, 1.0 + seq0 * 0.003
    for _ in range(count):
        d = _valid(c, seq, t0)
        n = len(d["t"])
        seq, t0 = max(0, seq + n + c.pick([0, 0, 0, 1, -2 * n])), t0 + 0.003 * n  # a jump back, never below 0
        if c.integer(0, 2) == 0:
            out.append((T.samples_key(PREFIX, d["machine"], d["axis"]), _encode(d), True))
        else:
            m = _mutate(c, d)
            out.append((_key_for(c, m, True), _encode(m), False))
    return out


# ---- the oracle of "unchanged" and "within the contract" --------------------------------------------
def _plain(payload: bytes) -> dict:
    return json.loads(payload)


def _same(block: S.SampleBlock, plain: dict) -> bool:
    if (block.machine, block.axis, block.seq) != (plain["machine"], plain["axis"], plain["seq"]):
        return False
    if block.t != [float(x) for x in plain["t"]]:
        return False
    for col in COLUMNS:
        got, want = getattr(block, col), plain.get(col)
        if want is None:
            if got is not None:
                return False
        elif got != [None if x is None else float(x) for x in want]:
            return False
    return True


def _in_contract(block: S.SampleBlock) -> bool:
    n = len(block.t)
    return (NAME_RE.fullmatch(block.machine) is not None and NAME_RE.fullmatch(block.axis) is not None
            and 0 <= block.seq and block.seq + n - 1 <= SEQ_MAX and all(0.0 <= x <= T_MAX for x in block.t))


def _outcomes(mon: Monitor, ax) -> dict[str, int]:
    st = mon.status()
    a = st["axes"][f"{MACHINE}/{AXIS_NAME}"]
    return {"malformed": st["input"]["malformed"] + a["drops"].get("malformed", 0),
            "key_mismatch": st["input"]["key_mismatch_total"],
            "no_model": st["input"]["no_model_blocks"],
            "routed": a["blocks"]}


# ---- in process: hypothesis ------------------------------------------------------------------------
class _Capture:
    name = "capture"

    def __init__(self):
        self.items = []

    def offer(self, item):
        self.items.append(item)
        return True

    def close(self, timeout=None):
        return True

    def status(self):
        return {"name": self.name, "state": "ok", "accepted": len(self.items), "written": 0, "dropped": 0,
                "failures": 0, "pending": 0}


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    write_trial(simulate(load_scenario("shaker-constant", duration=1.0), seed=2), d / "trial.mcap")
    model_from_truth(d / "trial.mcap", d / "z.model.toml")
    axes = load_axes([d / "z.model.toml"])
    warm_up(axes)
    ax = axes[(MACHINE, AXIS_NAME)]
    sink = _Capture()
    with T.open_session(listen=f"tcp/127.0.0.1:{T.free_tcp_port()}") as session:
        mon = Monitor(axes, session, prefix=PREFIX, sinks=[sink])
        mon.start()
        try:
            yield {"mon": mon, "ax": ax, "sink": sink, "ref": AxisEstimator(ax.model), "d": d}
        finally:
            assert mon.stop() == []


@settings(max_examples=300, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_every_message_has_one_counted_outcome_and_accepted_data_is_unchanged(rig, data):
    mon, ax, sink, ref = rig["mon"], rig["ax"], rig["sink"], rig["ref"]
    c = _Draw(data)
    for key, payload, built_valid in messages(c, c.integer(1, 8), seq0=c.integer(0, 10**6)):
        before = _outcomes(mon, ax)
        n_items = len(sink.items)
        est = mon.handle(key, payload, time.perf_counter())  # must not raise
        after = _outcomes(mon, ax)
        delta = {k: after[k] - before[k] for k in after}
        assert sum(delta.values()) == 1 and all(v in (0, 1) for v in delta.values()), (delta, key, payload[:300])
        if built_valid:
            assert delta["malformed"] == delta["key_mismatch"] == 0, (delta, payload[:300])
        if delta["routed"]:
            block = sink.items[n_items]
            assert isinstance(block, S.SampleBlock) and _in_contract(block), block
            assert _same(block, _plain(payload)), (block, payload[:300])
            want = ref.process(S.decode_samples(payload))
            assert (est is None) == (want is None)
            if est is not None:
                assert S.encode(est) == S.encode(want)  # bit for bit: same code, same process
                assert sink.items[n_items + 1] is est
        else:
            assert len(sink.items) == n_items and est is None  # a refused message reaches no sink
    assert mon.status()["input"]["internal_errors"] == 0
    mine, theirs = ax.estimator.snapshot(), ref.snapshot()
    assert mine.keys() == theirs.keys()
    for k in theirs:
        assert (mine[k] == theirs[k]).all() or (mine[k].dtype.kind == "f" and (
            (mine[k] == theirs[k]) | (mine[k] != mine[k]) & (theirs[k] != theirs[k]))).all(), k
    sink.items.clear()


# ---- a real daemon: a seeded batch through Zenoh ------------------------------------------------------
def test_feedmon_run_survives_a_fuzzed_batch_and_counts_every_message(rig):
    d = rig["d"]
    batch = messages(_Random(20240611), 600)
    mon = MonitorProc(prefix=PREFIX, args=["--model", "z.model.toml", "--fresh", "--state-dir", str(d / "st")], cwd=d)
    try:
        with T.open_session(connect=mon.endpoint) as s:
            pub = s.declare_publisher(T.samples_key(PREFIX, MACHINE, AXIS_NAME))
            assert T.wait_for_matching(pub, 15.0)
            for key, payload, _ in batch:
                s.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
            st = wait_status(s, pid=mon.proc.pid, timeout=60,
                             pred=lambda x: x["input"]["handled"] == len(batch))
    finally:
        rc = mon.stop()
    assert rc == 0, mon.stderr
    inp = st["input"]
    a = st["axes"][f"{MACHINE}/{AXIS_NAME}"]
    assert inp["received"] == len(batch) and inp["internal_errors"] == 0 and inp["too_large"] == 0
    outcomes = inp["malformed"] + a["drops"].get("malformed", 0) + inp["key_mismatch_total"] + inp["no_model_blocks"] \
        + a["blocks"]
    assert outcomes == len(batch), st
    assert inp["malformed"] + a["drops"].get("malformed", 0) > 100 and a["blocks"] > 100  # both kinds were there
    assert "Traceback" not in mon.stderr
