"""kernels.layout: one field list per compiled state, from which the NamedTuple, the offsets, the NumPy
views, the compiled accessors and the snapshot fields all come — a field added in one place only fails here."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit

from kernels import KRLST, LocallyPeriodic, online
from kernels import _krlst_core as core
from kernels import beta_layout as bl
from kernels import health as hl
from kernels.beta_tracker import OnlineBeta
from kernels.layout import Field, Layout, Record

TS = 0.003
NAMES = ("v_ref", "v_meas", "-sigma_p", "-sigma_n", "one")
BETA0 = np.array([0.02, 0.95, 1e-4, -1e-4, 1e-5])


def _addr(a: np.ndarray) -> int:
    return a.__array_interface__["data"][0]


def _check_views(layout: Layout, views, fbuf, ibuf, dims: dict):
    """Every field of the spec, in spec order, of its shape and dtype, inside its buffer, none overlapping,
    and the buffers no longer than the fields (with the padding) need."""
    assert type(views)._fields == tuple(f.name for f in layout.fields)
    spans = {"f": [], "i": []}
    for f in layout.fields:
        v = getattr(views, f.name)
        assert v.shape == layout.shape(f, dims), f.name
        kind = "f" if f.dtype == "f8" else "i"
        buf = fbuf if kind == "f" else ibuf
        assert v.dtype == buf.dtype and np.shares_memory(v, buf), f.name
        start = (_addr(v) - _addr(buf)) // 8
        spans[kind].append((start, start + v.size, f.name))
    for kind, buf in (("f", fbuf), ("i", ibuf)):
        s = sorted(spans[kind])
        for (_, a1, n1), (b0, _, n2) in zip(s, s[1:]):
            assert a1 <= b0, f"{n1} overlaps {n2}"
        if s:
            assert s[-1][1] <= buf.size
            used = sum(b - a for a, b, _ in s)
            assert buf.size - used < layout.align * len(s) + 1   # only padding beyond the fields


def _check_compiled(accessor, layout: Layout, fbuf, ibuf):
    """The compiled accessor gives the same fields at the same addresses and shapes as the NumPy views."""
    got = njit(lambda f, i: accessor(f, i))(fbuf, ibuf)   # the buffers stay alive for the comparison
    ref = layout.views(fbuf, ibuf)
    assert type(got)._fields == type(ref)._fields
    for name in ref._fields:
        a, b = getattr(got, name), getattr(ref, name)
        assert a.shape == b.shape and a.dtype == b.dtype and _addr(a) == _addr(b), name


def _tracker(budget=12):
    return KRLST(LocallyPeriodic(1.2, 0.495, 1 / 55), gamma=5.85, forgetting=0.996, budget=budget, grid_step=TS)


def test_core_state_is_its_field_list():
    tr = _tracker()
    x = np.array([0.0])
    fbuf, ibuf = tr.core_buffers(x)
    st = core.state_views(fbuf, ibuf)
    dims = dict(zip(core.LAYOUT.dims, (int(v) for v in ibuf[:5])))
    _check_views(core.LAYOUT, st, fbuf, ibuf, dims)
    assert all(_addr(getattr(st, f.name)) % 64 == 0 for f in core.FIELDS if f.dtype == "f8")   # 8-lane rows
    _check_compiled(core.state_of, core.LAYOUT, fbuf, ibuf)
    assert core.STATE_FIELDS == tuple(f.name for f in core.FIELDS if f.role == "state")
    for k in range(30):
        tr.learn_one(k * TS, math.sin(k / 5.0))
    snap = tr.snapshot()
    assert set(core.STATE_FIELDS) <= set(snap)
    assert not set(snap) & set(core.LAYOUT.names("scratch", "layout"))


def test_beta_state_is_its_field_list():
    tr = _tracker()
    ob = OnlineBeta(tr, BETA0, NAMES, TS, omega=1e-3)
    fbuf, ibuf = ob._buf
    dims = dict(zip(bl.LAYOUT.dims, (int(v) for v in ibuf[:3])))
    _check_views(bl.LAYOUT, ob.state, fbuf, ibuf, dims)
    _check_compiled(bl.beta_state_of, bl.LAYOUT, fbuf, ibuf)
    assert bl.STATE_FIELDS == bl.LAYOUT.names("state") and bl.SETTINGS_FIELDS == bl.LAYOUT.names("setting")
    assert set(ob.snapshot()) == {f"beta.{n}" for n in bl.STATE_FIELDS}


def test_health_state_is_its_field_list():
    k = len(hl.PARAMS)
    mon = hl.HealthMonitor(TS, np.ones(k), np.ones(k), np.ones(k))
    fbuf, ibuf = hl.new_health_buffers(TS, np.ones(k), np.ones(k), np.ones(k), np.ones(k))
    _check_views(hl.LAYOUT, hl.health_state_views(fbuf, ibuf), fbuf, ibuf, {})
    _check_compiled(hl.health_state_of, hl.LAYOUT, fbuf, ibuf)
    assert set(mon.snapshot()) == {f"health.{n}" for n in hl.STATE_FIELDS}
    assert hl.STATE_FIELDS == hl.LAYOUT.names("state")


def test_online_state_and_config_are_their_field_lists():
    buf = online.new_state(trained=7)
    st = online.state_of(*buf)
    assert type(st)._fields == tuple(f.name for f in online.STATE_SPEC)
    ints = [f.name for f in online.STATE_SPEC if f.dtype == "i8"]
    assert buf.ints.size == len(ints) and buf.floats.size == len(online.STATE_SPEC) - len(ints)
    assert st.trained[0] == 7 and np.shares_memory(st.trained, buf.ints) and np.isnan(buf.floats).all()
    compiled = njit(lambda i, f: online.state_of(i, f).tick_t[0] + online.state_of(i, f).trained[0])
    buf.floats[-1] = 1.5
    assert compiled(*buf) == 8.5

    values = dict(coulomb=True, intercept=False, omega=0.01, inv_ts=1 / TS, v_max=2.0, e_max=3.0, t_max=1e6,
                  stale_detection=True, warmup=9, reorder_window=64, mode="apply", spindle=True, theta_period=1.5,
                  rpm_nominal=3000.0, rpm_max=1e5, tick_period=1.0)
    cfg = online.new_config(beta=BETA0, **values)
    named = online.config_of(*cfg)
    assert named._fields == ("beta",) + tuple(f.name for f in online.CONFIG_SPEC)
    values["mode"] = online.ADAPTATION_MODES.index("apply")
    values["tick_min"] = max(1, round(0.5 / TS))
    for name, v in values.items():
        assert getattr(named, name) == v, name
    assert cfg.ints.size + cfg.floats.size == len(online.CONFIG_SPEC)
    in_njit = njit(lambda b, i, f: online.config_of(b, i, f).rpm_nominal)(*cfg)
    assert in_njit == 3000.0
    online.set_tracker_input(cfg, False, 2.0, rpm_nominal=100.0)
    named = online.config_of(*cfg)
    assert (named.spindle, named.theta_period, named.rpm_nominal) == (False, 2.0, 100.0)


def test_placement_padding_and_a_new_field_reach_every_product():
    fields = (Field("hdr", "i8", (2,), "layout"), Field("a", "f8", ("n",), "state"),
              Field("m", "f8", ("n", 3), "scratch"), Field("k", "i8", ("n + 1",), "setting"))
    lay = Layout("Demo", __name__, fields, dims=("n",), align=4, placement=("hdr", "k", "m", "a"))
    at, nf, ni = lay.offsets(n=5)
    assert at == {"hdr": 0, "k": 2, "m": 0, "a": 16} and (nf, ni) == (24, 8)
    fbuf, ibuf = lay.new_buffers(n=5)
    assert ibuf[0] == 5
    _check_views(lay, lay.views(fbuf, ibuf), fbuf, ibuf, {"n": 5})
    _check_compiled(lay.accessor("demo_of", __file__), lay, fbuf, ibuf)
    grown = Layout("Demo", __name__, fields + (Field("b", "f8", (2,), "state"),), dims=("n",), align=4)
    fbuf, ibuf = grown.new_buffers(n=5)
    views = grown.views(fbuf, ibuf)
    assert views.b.shape == (2,) and grown.names("state") == ("a", "b")
    _check_views(grown, views, fbuf, ibuf, {"n": 5})
    _check_compiled(grown.accessor("grown_of", __file__), grown, fbuf, ibuf)


def test_a_spec_that_contradicts_itself_is_refused():
    with pytest.raises(ValueError, match="duplicate"):
        Layout("Bad", __name__, (Field("a", "f8", (1,), "state"), Field("a", "i8", (1,), "state")))
    with pytest.raises(ValueError, match="placement"):
        Layout("Bad", __name__, (Field("a", "f8", (1,), "state"),), placement=("a", "b"))
    with pytest.raises(ValueError, match="role"):
        Layout("Bad", __name__, (Field("a", "f8", (1,), "stat"),))
    with pytest.raises(ValueError, match="scalars"):
        Record("Bad", __name__, (Field("a", "f8", (2,), "setting"),))
    rec = Record("Rec", __name__, (Field("a", "f8", (), "setting"), Field("b", "bool", (), "setting")))
    with pytest.raises(ValueError, match="no value for"):
        rec.pack(a=1.0)


def test_shape_expressions_parse_once_and_from_several_threads():
    """The disturbance search builds trackers (and their layouts) on a worker thread while the estimator
    builds its own: CPython 3.11's parser is not safe for that (python/cpython#106905), so each expression
    is parsed once, under a lock, and every thread gets the right values."""
    import threading

    from kernels import layout as L

    exprs = [f"p * {k} + cap - {k % 7}" for k in range(300)]
    errors, results = [], {}

    def work(offset: int) -> None:
        try:
            for k in range(offset, offset + 300):
                e = exprs[k % 300]
                results[(offset, k)] = L._dimension(e, {"p": 3, "cap": 100}) == 3 * (k % 300) + 100 - (k % 300) % 7
        except Exception as exc:  # noqa: BLE001 - the test reports whatever a thread raised
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(37 * i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and len(results) == 2400 and all(results.values())
    assert L._parsed(exprs[5]) is L._parsed(exprs[5])
