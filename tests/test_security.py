"""Security defaults: loopback only, TLS with mutual authentication, access control, no code from data.

The TLS/ACL part runs a real Zenoh router (zenoh-python, mode "router") from the
example config ``deploy/zenoh/router.json5`` and real clients from
``deploy/zenoh/*-client.json5`` — the files the documentation shows — with
certificates made at test time by ``deploy/tls/make_certs.py`` (openssl CLI).
Only the certificate directory and the endpoints are substituted.
"""

from __future__ import annotations

import argparse
import importlib.util
import io
import ipaddress
import json
import os
import queue
import re
import shutil
import time
import tokenize
from pathlib import Path

import pytest
import zenoh

from feedio import transport as T
from feedio.transport import query_status

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy" / "zenoh"
CERT_DIR_PLACEHOLDER = "/etc/feedmon/tls"
ROUTER_LISTEN_PLACEHOLDER = "tls/0.0.0.0:7447"
CLIENT_CONNECT_PLACEHOLDER = "tls/feedmon-router:7447"
ARRIVE = 5.0  # s: upper bound for data that must arrive
QUIET = 0.5  # s: extra wait, after a later allowed message arrived, for data that must NOT arrive


# ============================================================================================
# loopback only, no multicast, unless configured
# ============================================================================================
def _loopback(endpoint: str) -> bool:
    m = re.match(r"^[a-z0-9+-]+/(.+):(\d+)$", endpoint)
    assert m, f"unexpected endpoint {endpoint!r}"
    host = m.group(1).strip("[]")
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def _cfg(cfg: zenoh.Config, key: str):
    return json.loads(cfg.get_json(key))


def test_default_config_listens_on_loopback_only_and_multicast_is_off():
    for kwargs in ({}, {"mode": "peer"}, {"connect": T.DEFAULT_ENDPOINT}, {"listen": T.DEFAULT_ENDPOINT}):
        cfg = T.zenoh_config(**kwargs)
        listen = _cfg(cfg, "listen/endpoints")
        assert listen and all(_loopback(ep) for ep in listen), (kwargs, listen)
        assert _cfg(cfg, "scouting/multicast/enabled") is False, kwargs
    cfg = T.zenoh_config(mode="client", connect="tcp/127.0.0.1:7448")
    assert _cfg(cfg, "scouting/multicast/enabled") is False
    assert T.DEFAULT_ENDPOINT.startswith("tcp/127.0.0.1:")


@pytest.mark.parametrize("role", ["listen", "connect"])
def test_cli_defaults_are_loopback_only(role):
    """What ``feedmon run`` (listen) and publishers/tools (connect) open without options."""
    p = argparse.ArgumentParser()
    T.add_zenoh_arguments(p, role=role)
    cfg = T.config_from_args(p.parse_args([]))  # exactly what session_from_args opens
    listen, connect = _cfg(cfg, "listen/endpoints"), _cfg(cfg, "connect/endpoints")
    assert listen and all(_loopback(ep) for ep in listen), listen
    assert all(_loopback(ep) for ep in connect), connect
    assert _cfg(cfg, "scouting/multicast/enabled") is False
    if role == "listen":
        assert listen == [T.DEFAULT_ENDPOINT]


def _own_listening_sockets() -> set[tuple[str, int]]:
    """(address, port) of TCP sockets of this process in LISTEN state (Linux /proc)."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    out = set()
    for table, v6 in (("/proc/net/tcp", False), ("/proc/net/tcp6", True)):
        if not os.path.exists(table):
            continue
        with open(table) as f:
            next(f)
            for line in f:
                parts = line.split()
                local, state, inode = parts[1], parts[3], parts[9]
                if state != "0A" or inode not in inodes:
                    continue
                addr_hex, port_hex = local.split(":")
                raw = bytes.fromhex(addr_hex)
                if v6:
                    raw = b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4))
                    addr = str(ipaddress.IPv6Address(raw))
                else:
                    addr = str(ipaddress.IPv4Address(raw[::-1]))
                out.add((addr, int(port_hex, 16)))
    return out


@pytest.mark.skipif(not os.path.exists("/proc/self/fd"), reason="needs Linux /proc to list sockets")
def test_default_session_really_listens_on_loopback_only():
    before = _own_listening_sockets()
    s = T.open_session()  # feedmon's default peer session
    try:
        new = _own_listening_sockets() - before
    finally:
        s.close()
    assert new, "the default session should listen on an ephemeral loopback port"
    assert all(ipaddress.ip_address(a).is_loopback for a, _ in new), new


# ============================================================================================
# TLS with mutual authentication and access control, from the deploy/zenoh example files
# ============================================================================================
def _load_make_certs():
    spec = importlib.util.spec_from_file_location("feedmon_make_certs", REPO / "deploy" / "tls" / "make_certs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    if shutil.which("openssl") is None:
        pytest.fail("the openssl command is needed to make test certificates (apt-get install openssl)", pytrace=False)
    mc = _load_make_certs()
    good = tmp_path_factory.mktemp("tls")
    made = mc.make_cell(good, clients=("monitor", "controller", "viewer"))
    # an attacker's CA and a client certificate with the *same* CN as the real controller
    evil = tmp_path_factory.mktemp("tls-foreign")
    evil_ca = mc.make_ca(evil, cn="foreign CA")
    mc.make_cert(evil, "controller", evil_ca)
    return {"dir": good, "foreign": evil, "made": made}


def _fill(name: str, cert_dir: Path, port: int, out: Path) -> Path:
    """The example config ``deploy/zenoh/<name>`` with certificate directory and endpoints filled in."""
    text = (DEPLOY / name).read_text()
    assert CERT_DIR_PLACEHOLDER in text, f"{name} no longer uses {CERT_DIR_PLACEHOLDER}: update this test"
    text = text.replace(CERT_DIR_PLACEHOLDER, str(cert_dir))
    placeholder = ROUTER_LISTEN_PLACEHOLDER if name == "router.json5" else CLIENT_CONNECT_PLACEHOLDER
    assert placeholder in text, f"{name} no longer uses {placeholder}: update this test"
    text = text.replace(placeholder, f"tls/127.0.0.1:{port}")
    out.mkdir(parents=True, exist_ok=True)
    path = out / name
    path.write_text(text)
    return path


class Cell:
    """A router from router.json5 and the filled client configs."""

    def __init__(self, pki, out: Path, *, acl: bool = True, viewer_sees_sample_subscribers: bool = False):
        self.port = T.free_tcp_port()
        self.out = out
        self.files = {n: _fill(n, pki["dir"], self.port, out) for n in
                      ("router.json5", "monitor-client.json5", "controller-client.json5", "viewer-client.json5")}
        cfg = zenoh.Config.from_file(str(self.files["router.json5"]))
        if not acl:
            cfg.insert_json5("access_control/enabled", "false")
        if viewer_sees_sample_subscribers:  # test variant: the viewer's client believes it has a subscriber
            policies = _cfg(cfg, "access_control/policies")
            for p in policies:
                if p["subjects"] == ["viewer"]:
                    p["rules"].append("samples-announce")
            cfg.insert_json5("access_control/policies", json.dumps(policies))
        self.router = zenoh.open(cfg)
        self.sessions: list[zenoh.Session] = []

    def config(self, role: str) -> zenoh.Config:
        """The client config of ``role`` as feedmon loads it (``--zenoh-config FILE``)."""
        return T.zenoh_config(config_file=self.files[f"{role}-client.json5"], mode=None, multicast_scouting=None)

    def open(self, role_or_config) -> zenoh.Session:
        cfg = self.config(role_or_config) if isinstance(role_or_config, str) else role_or_config
        s = T.open_session(cfg)
        self.sessions.append(s)
        return s

    def close_clients(self):
        while self.sessions:
            self.sessions.pop().close()

    def close(self):
        self.close_clients()
        self.router.close()


@pytest.fixture(scope="module")
def _router(pki, tmp_path_factory):
    c = Cell(pki, tmp_path_factory.mktemp("zenoh-cfg"))
    yield c
    c.close()


@pytest.fixture
def cell(_router):
    """The module's router; the clients a test opens are closed after it."""
    yield _router
    _router.close_clients()


class Inbox:
    """Subscriber callback target: payloads by key, waitable."""

    def __init__(self):
        self.q: queue.Queue = queue.Queue()
        self.seen: list[tuple[str, bytes]] = []

    def __call__(self, sample):
        self.q.put((str(sample.key_expr), sample.payload.to_bytes()))

    def wait_for(self, payload: bytes, timeout: float = ARRIVE) -> bool:
        deadline = time.monotonic() + timeout
        while True:
            if any(p == payload for _, p in self.seen):
                return True
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            try:
                self.seen.append(self.q.get(timeout=left))
            except queue.Empty:
                return False

    def drain(self, quiet: float = QUIET) -> list[bytes]:
        time.sleep(quiet)
        while True:
            try:
                self.seen.append(self.q.get_nowait())
            except queue.Empty:
                return [p for _, p in self.seen]


def test_deploy_configs_are_strict():
    """The example files themselves: TLS only, mTLS, ACL default deny, clients never listen, no multicast."""
    router = zenoh.Config.from_file(str(DEPLOY / "router.json5"))
    assert _cfg(router, "mode") == "router"
    assert _cfg(router, "transport/link/protocols") == ["tls"]
    assert _cfg(router, "transport/link/tls/enable_mtls") is True
    assert _cfg(router, "scouting/multicast/enabled") is False
    assert _cfg(router, "access_control/enabled") is True
    assert _cfg(router, "access_control/default_permission") == "deny"
    subjects = _cfg(router, "access_control/subjects")
    assert {s["id"]: s["cert_common_names"] for s in subjects} == {
        "monitor": ["monitor"], "controller": ["controller"], "viewer": ["viewer"]}
    for role in ("monitor", "controller", "viewer"):
        c = zenoh.Config.from_file(str(DEPLOY / f"{role}-client.json5"))
        assert _cfg(c, "mode") == "client"
        assert _cfg(c, "listen/endpoints") == []
        assert _cfg(c, "transport/link/protocols") == ["tls"]
        tls = _cfg(c, "transport/link/tls")
        assert tls["enable_mtls"] is True and tls["verify_name_on_connect"] is True
        assert tls["connect_certificate"].endswith(f"/{role}.pem")
        assert _cfg(c, "scouting/multicast/enabled") is False


def test_mtls_client_with_right_certificate_gets_through(cell):
    t0 = time.monotonic()
    monitor, controller = cell.open("monitor"), cell.open("controller")
    assert time.monotonic() - t0 < 5.0
    assert monitor.info.routers_zid() and controller.info.routers_zid()
    inbox = Inbox()
    monitor.declare_subscriber(T.samples_key(), inbox)
    pub = controller.declare_publisher(T.samples_key(machine="mill", axis="X"))
    assert T.wait_for_matching(pub, ARRIVE), "the controller never saw the monitor's subscriber"
    pub.put(b"sample-1")
    assert inbox.wait_for(b"sample-1"), "samples did not flow controller -> router -> monitor over mTLS"


def _expect_refused(cell, cfg: zenoh.Config, what: str) -> str:
    t0 = time.monotonic()
    with pytest.raises(OSError, match="cannot open Zenoh session") as exc:
        s = T.open_session(cfg)
        s.close()  # pragma: no cover - only reached when the test fails
    assert time.monotonic() - t0 < 5.0, f"{what}: refusal took too long"
    return str(exc.value)


def test_clients_without_valid_certificate_are_refused(cell, pki):
    # 1. no client certificate at all (mTLS off on the client side, no key/cert)
    cfg = cell.config("controller")
    cfg.insert_json5("transport/link/tls/enable_mtls", "false")
    cfg.insert_json5("transport/link/tls/connect_certificate", "null")
    cfg.insert_json5("transport/link/tls/connect_private_key", "null")
    _expect_refused(cell, cfg, "no certificate")
    # 2. certificate paths given but mTLS not enabled on the client: it presents nothing either
    cfg = cell.config("controller")
    cfg.insert_json5("transport/link/tls/enable_mtls", "false")
    _expect_refused(cell, cfg, "client enable_mtls false")
    # 3. a certificate with the right CN ("controller") from a foreign CA
    foreign = pki["foreign"]
    cfg = cell.config("controller")
    cfg.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(foreign / "controller.pem")))
    cfg.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(foreign / "controller-key.pem")))
    _expect_refused(cell, cfg, "foreign CA")
    # 4. a client that does not trust the router's CA refuses the router (server authentication)
    cfg = cell.config("controller")
    cfg.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(foreign / "ca.pem")))
    _expect_refused(cell, cfg, "router not trusted")
    # 5. plain TCP to the TLS port
    cfg = T.zenoh_config(mode="client", connect=f"tcp/127.0.0.1:{cell.port}")
    _expect_refused(cell, cfg, "plain tcp")


def test_acl_viewer_reads_disturbance_but_cannot_publish_samples(cell):
    monitor, controller, viewer = cell.open("monitor"), cell.open("controller"), cell.open("viewer")
    samples_in, disturbance_in = Inbox(), Inbox()
    monitor.declare_subscriber(T.samples_key(), samples_in)
    monitor.declare_queryable(T.status_key(), lambda q: q.reply(T.status_key(), b'{"ok": true}'))
    viewer.declare_subscriber("feedmon/**/disturbance", disturbance_in)

    # allowed: monitor -> viewer on feedmon/**/disturbance
    est = monitor.declare_publisher(T.disturbance_key(machine="mill", axis="X"))
    assert T.wait_for_matching(est, ARRIVE), "the monitor never saw the viewer's disturbance subscriber"
    est.put(b"estimate-1")
    assert disturbance_in.wait_for(b"estimate-1"), "viewer did not receive disturbance estimates"

    # denied: viewer -> feedmon/**/samples (publisher and plain put); controller's sample is the barrier
    ctl = controller.declare_publisher(T.samples_key(machine="mill", axis="X"))
    assert T.wait_for_matching(ctl, ARRIVE)
    forged = viewer.declare_publisher(T.samples_key(machine="mill", axis="X"))
    assert not forged.matching_status.matching, "the router announced the samples subscriber to a viewer"
    forged.put(b"forged-1")
    viewer.put(T.samples_key(machine="mill", axis="X"), b"forged-2")
    ctl.put(b"genuine-1")
    assert samples_in.wait_for(b"genuine-1")
    got = samples_in.drain()
    assert b"forged-1" not in got and b"forged-2" not in got, "a viewer certificate could publish samples"

    # a viewer may ask for the monitor status, a controller may not
    assert query_status(viewer, timeout=ARRIVE) == [{"ok": True}]
    assert query_status(controller, timeout=1.0) == []

    # a controller cannot read the estimates
    snoop = Inbox()
    controller.declare_subscriber("feedmon/**/disturbance", snoop)
    time.sleep(0.2)
    est.put(b"estimate-2")
    assert disturbance_in.wait_for(b"estimate-2")
    assert b"estimate-2" not in snoop.drain()


def test_cli_status_with_the_viewer_config(cell, capsys):
    """As documented: ``feedmon status --zenoh-config viewer-client.json5`` works, with the controller's it gets nothing."""
    from feedmon.cli import main

    monitor = cell.open("monitor")
    monitor.declare_queryable(T.status_key(), lambda q: q.reply(T.status_key(), b'{"monitor": "m1"}'))
    argv = ["status", "--json", "--zenoh-config"]
    assert main(argv + [str(cell.files["viewer-client.json5"]), "--timeout", str(ARRIVE)]) == 0
    assert json.loads(capsys.readouterr().out) == [{"monitor": "m1"}]
    assert main(argv + [str(cell.files["controller-client.json5"]), "--timeout", "1"]) == 1
    assert "no monitor answered" in capsys.readouterr().err


@pytest.mark.parametrize("acl", [True, False], ids=["acl", "no-acl"])
def test_acl_denies_viewer_puts_at_the_router(pki, tmp_path, acl):
    """The denial is enforced on the router's ingress, not only by the viewer's client not sending.

    Variant of router.json5 in which the viewer is told about the samples subscriber, so its
    client really sends the puts: with access control they still never arrive; with
    ``access_control.enabled = false`` (control experiment) the same puts do arrive.
    """
    c = Cell(pki, tmp_path, acl=acl, viewer_sees_sample_subscribers=True)
    try:
        monitor, controller, viewer = c.open("monitor"), c.open("controller"), c.open("viewer")
        inbox = Inbox()
        monitor.declare_subscriber(T.samples_key(), inbox)
        forged = viewer.declare_publisher(T.samples_key(machine="mill", axis="X"))
        assert T.wait_for_matching(forged, ARRIVE), "the viewer's client should see the subscriber here"
        ctl = controller.declare_publisher(T.samples_key(machine="mill", axis="X"))
        assert T.wait_for_matching(ctl, ARRIVE)
        forged.put(b"forged-1")
        ctl.put(b"genuine-1")
        assert inbox.wait_for(b"genuine-1")
        if acl:
            assert b"forged-1" not in inbox.drain(), "the router let a viewer's put on samples through"
        else:
            assert inbox.wait_for(b"forged-1"), "control: without access control the put should arrive"
    finally:
        c.close()


# ============================================================================================
# nothing read from disk or wire is executed or unpickled
# ============================================================================================
_FORBIDDEN_MODULES = {"pickle", "cPickle", "_pickle", "dill", "cloudpickle", "shelve", "marshal", "joblib"}
_YAML_UNSAFE = {"load", "load_all", "unsafe_load", "unsafe_load_all", "full_load", "full_load_all"}


def find_unsafe_code(source: str) -> list[tuple[int, str]]:
    """(line, what) of every unsafe construct in Python ``source``.

    Works on tokens, so comments and strings (docstrings saying "never pickle") are
    ignored: ``import pickle`` / any use of pickle-like modules, calls of the builtins
    ``eval(`` / ``exec(`` (not methods such as ``model.eval()``), ``allow_pickle=True``,
    ``yaml.load(`` and the other non-safe YAML loaders, ``yaml.Loader`` / ``UnsafeLoader``.
    """
    toks = [t for t in tokenize.generate_tokens(io.StringIO(source).readline)
            if t.type not in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT,
                              tokenize.DEDENT, tokenize.STRING)]
    hits = []
    for i, t in enumerate(toks):
        if t.type != tokenize.NAME:
            continue
        prev = toks[i - 1].string if i else ""
        nxt = toks[i + 1].string if i + 1 < len(toks) else ""
        nxt2 = toks[i + 2].string if i + 2 < len(toks) else ""
        nxt3 = toks[i + 3].string if i + 3 < len(toks) else ""
        line = t.start[0]
        if t.string in _FORBIDDEN_MODULES and prev != ".":
            hits.append((line, t.string))
        elif t.string in ("eval", "exec") and nxt == "(" and prev not in (".", "def"):
            hits.append((line, f"{t.string}("))
        elif t.string == "allow_pickle" and nxt == "=" and nxt2 != "False":
            hits.append((line, f"allow_pickle={nxt2}"))
        elif t.string == "yaml" and nxt == "." and (nxt2 in _YAML_UNSAFE and nxt3 == "(" or nxt2 in ("Loader", "UnsafeLoader")):
            hits.append((line, f"yaml.{nxt2}"))
    return hits


def test_unsafe_code_finder_is_precise():
    bad = (
        "import pickle\n"
        "from pickle import loads\n"
        "x = eval(s)\n"
        "exec (code)\n"
        "a = np.load(f, allow_pickle=True)\n"
        "cfg = yaml.load(s)\n"
        "cfg = yaml.load(s, Loader=yaml.Loader)\n"
        "import dill as d\n"
    )
    whats = [w for _, w in find_unsafe_code(bad)]
    assert whats == ["pickle", "pickle", "eval(", "exec(", "allow_pickle=True", "yaml.load", "yaml.load",
                     "yaml.Loader", "dill"]
    good = (
        '"""Never pickle, never eval( or exec( anything; allow_pickle=True is forbidden; yaml.load( too."""\n'
        "# import pickle  -- no\n"
        "z = np.load(path, allow_pickle=False)\n"
        "y = yaml.safe_load(s)\n"
        "model.eval()\n"
        "msg = 'use pickle? no'\n"
        "def eval(self):\n"
        "    return 1\n"
    )
    assert find_unsafe_code(good) == []


#: code generation, not data: ``kernels/layout.py`` compiles the accessors of each compiled state from the
#: field list written in the code (as ``collections.namedtuple`` does); no input of any kind reaches it,
#: and its shape expressions are parsed (``ast``), never evaluated
CODEGEN = {("kernels/layout.py", "exec(")}


def test_package_never_unpickles_or_evaluates_data():
    found = []
    files = 0
    for pkg in ("kernels", "monitor", "replay"):
        for path in sorted((REPO / pkg).rglob("*.py")):
            files += 1
            for line, what in find_unsafe_code(path.read_text(encoding="utf-8")):
                if (path.relative_to(REPO).as_posix(), what) not in CODEGEN:
                    found.append(f"{path.relative_to(REPO)}:{line}: {what}")
    assert files > 10
    assert not found, "unsafe deserialisation / evaluation in the package:\n" + "\n".join(found)
