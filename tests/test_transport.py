"""Zenoh transport: two real sessions on loopback (peer mode, multicast off) exchange blocks."""

from __future__ import annotations

import argparse
import json
import queue
import time

import pytest
import zenoh

from feedio import schema as S
from feedio import transport as T

WAIT = 10.0  # s, upper bound of every wait


def _block(seq: int, n: int = 5) -> S.SampleBlock:
    t = [(seq + i) / 333.0 for i in range(n)]
    return S.SampleBlock(machine="mill", axis="X", seq=seq, t=t, v_ref=[0.01] * n, v_meas=[0.0099] * n)


@pytest.fixture
def pair():
    """(listener, connector): the monitor-side peer listens on a free loopback port, the other connects."""
    port = T.free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    a = T.open_session(listen=endpoint)
    b = None
    try:
        b = T.open_session(connect=endpoint)
        deadline = time.monotonic() + WAIT
        while not b.info.peers_zid() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert b.info.peers_zid(), "connecting peer did not reach the listening peer"
        yield a, b
    finally:
        if b is not None:
            b.close()
        a.close()


def test_config_defaults_peer_loopback_no_multicast():
    cfg = T.zenoh_config()
    assert json.loads(cfg.get_json("mode")) == "peer"
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    cfg = T.zenoh_config(mode="client", connect="tcp/10.0.0.1:7447,tcp/10.0.0.2:7447")
    assert json.loads(cfg.get_json("mode")) == "client"
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]


def test_config_errors_are_value_and_os_errors(tmp_path):
    with pytest.raises(ValueError, match="mode"):
        T.zenoh_config(mode="bogus")
    with pytest.raises(ValueError, match="not a Zenoh locator"):
        T.zenoh_config(connect="127.0.0.1:7447")
    with pytest.raises(FileNotFoundError):
        T.zenoh_config(config_file=tmp_path / "missing.json5")
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: 'nonsense' }")
    with pytest.raises(ValueError, match="invalid"):
        T.zenoh_config(config_file=bad)
    port = T.free_tcp_port()  # nobody listens there: a client fails at once
    with pytest.raises(OSError, match="cannot open Zenoh session"):
        T.open_session(mode="client", connect=f"tcp/127.0.0.1:{port}")


def test_listen_port_in_use_is_os_error():
    port = T.free_tcp_port()
    a = T.open_session(listen=f"tcp/127.0.0.1:{port}")
    try:
        with pytest.raises(OSError, match="listen"):
            T.open_session(listen=f"tcp/127.0.0.1:{port}")
    finally:
        a.close()


def test_config_file_is_base(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text("{ mode: 'client', connect: { endpoints: ['tcp/127.0.0.1:1'] } }")
    cfg = T.zenoh_config(mode=None, multicast_scouting=None, config_file=f)
    assert json.loads(cfg.get_json("mode")) == "client"
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:1"]


def test_keys():
    assert T.samples_key("feedmon", "mill", "X") == "feedmon/mill/X/samples"
    assert T.disturbance_key("feedmon", "mill", "X") == "feedmon/mill/X/disturbance"
    assert T.truth_key("p/q", "mill", "X") == "p/q/mill/X/truth"
    assert T.status_key() == "feedmon/monitor/status"
    assert T.samples_key() == "feedmon/*/*/samples"
    assert T.parse_key("feedmon/mill/X/samples") == ("mill", "X", "samples")
    for bad in ("a/b", "", "x*", "a b"):
        with pytest.raises(ValueError, match="key expression"):
            T.samples_key("feedmon", bad, "X")
    with pytest.raises(ValueError):
        T.parse_key("other/mill/X/samples")


def test_session_from_args_roles():
    ns = argparse.Namespace(connect=None, listen=None, mode="client", zenoh_config=None, multicast=False,
                            prefix="feedmon", _zenoh_role="listen")
    with pytest.raises(ValueError, match="--connect"):
        T.session_from_args(ns)


def test_peers_exchange_sample_blocks(pair):
    a, b = pair
    got: queue.Queue = queue.Queue()
    sub = a.declare_subscriber(T.samples_key("feedmon", "*", "*"),
                               lambda s: got.put((str(s.key_expr), s.payload.to_bytes())))
    pub = b.declare_publisher(T.samples_key("feedmon", "mill", "X"),
                              congestion_control=zenoh.CongestionControl.BLOCK)
    try:
        assert T.wait_for_matching(pub, WAIT), "subscription never propagated"
        n = 200
        for k in range(n):
            pub.put(S.encode(_block(5 * k)))
        blocks = []
        deadline = time.monotonic() + WAIT
        while len(blocks) < n and time.monotonic() < deadline:
            try:
                key, data = got.get(timeout=0.2)
            except queue.Empty:
                continue
            assert key == "feedmon/mill/X/samples"
            blocks.append(S.decode_samples(data))
        assert [b_.seq for b_ in blocks] == [5 * k for k in range(n)]  # all, in order
        assert blocks[7] == _block(35)
    finally:
        pub.undeclare()
        sub.undeclare()


def test_queryable_answers_json(pair):
    a, b = pair
    key = T.status_key("feedmon")
    status = {"state": "running", "axes": ["mill/X"], "dropped": 0}

    def answer(query: zenoh.Query) -> None:
        query.reply(key, json.dumps(status).encode(), encoding=zenoh.Encoding.APPLICATION_JSON)

    q = a.declare_queryable(key, answer)
    try:
        replies = []
        deadline = time.monotonic() + WAIT
        while not replies and time.monotonic() < deadline:  # the declaration needs a moment to propagate
            replies = [r.ok for r in b.get(key, timeout=2.0) if r.ok is not None]
            if not replies:
                time.sleep(0.05)
        assert replies, "no reply from the queryable"
        assert json.loads(replies[0].payload.to_bytes()) == status
        assert str(replies[0].key_expr) == key
    finally:
        q.undeclare()


def test_limit_message_size_drops_larger_messages_and_the_link_survives():
    """A listening session with a 1 MiB receive limit: a 2 MiB message never arrives (never reassembled),
    the messages before and after it do, in order, on the same link."""
    port = T.free_tcp_port()
    cfg = T.limit_message_size(T.zenoh_config(listen=f"tcp/127.0.0.1:{port}"), 1 << 20)
    got: queue.Queue = queue.Queue()
    with T.open_session(cfg) as m, T.open_session(connect=f"tcp/127.0.0.1:{port}") as s:
        m.declare_subscriber("feedmon/big/**", lambda x: got.put(len(x.payload)))
        pub = s.declare_publisher("feedmon/big/X", congestion_control=zenoh.CongestionControl.BLOCK)
        assert T.wait_for_matching(pub, WAIT)
        for size in (100, 2 << 20, 900 << 10, 101):
            pub.put(b"x" * size)
        sizes = []
        while 101 not in sizes:
            sizes.append(got.get(timeout=WAIT))
    assert sizes == [100, 900 << 10, 101]
    with pytest.raises(ValueError, match="message size limit"):
        T.limit_message_size(T.zenoh_config(), 0)
