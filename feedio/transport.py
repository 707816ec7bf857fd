"""Zenoh session setup and key expressions: the one place feedmon talks to Zenoh.

Who listens, who connects
-------------------------
Multicast scouting is OFF by default (it leaks onto the plant network and is
blocked in many cells), so two processes have to be told where to meet. feedmon
uses one fixed rendezvous endpoint, :data:`DEFAULT_ENDPOINT`
(``tcp/127.0.0.1:7448``, loopback only):

* the **monitor** (``feedmon run``) is a *peer* that **listens** on it;
* **publishers** and tools (controller bridge, ``feedmon replay``, status
  queries) are *peers* that **connect** to it. A connecting peer retries in the
  background, so the publisher may be started before the monitor (``feedmon
  replay`` additionally waits for a matching subscriber before sending).
  Connecting peers also listen on an ephemeral loopback port, so gossip
  scouting (on by default) can link further peers on the host directly.

The port is 7448, not Zenoh's 7447, so a ``zenohd`` router on the same host
never collides with the monitor. With a router (several hosts), every process
uses ``--connect tcp/<router>:7447``; an explicit ``--connect`` on the command
line makes the process a Zenoh *client* of that router (or of a monitor peer:
Zenoh 1.x peers accept clients), which fails at once with a clear error when the
endpoint is unreachable instead of retrying silently.

Key expressions
---------------
``<prefix>/<machine>/<axis>/samples|truth|disturbance`` and
``<prefix>/monitor/status`` with the default prefix ``feedmon`` (the MCAP
channels use the same tail without the prefix: ``/<machine>/<axis>/samples``).
A machine or axis of ``*`` (one chunk) or ``**`` gives a wildcard expression for
subscribers.

Notes on zenoh-python 1.x found while writing this
--------------------------------------------------
* ``Publisher.matching_status`` is a ``MatchingStatus`` object (always truthy);
  use ``.matching``. Declarations take a few ms to propagate: a ``put`` right
  after ``declare_publisher`` may reach nobody, and a ``get`` right after a
  remote ``declare_queryable`` may get no reply. Wait for ``matching`` / retry.
* ``Handler.recv()`` has no timeout; poll ``try_recv()`` or use a callback.
* ``transport/link/rx/max_message_size`` (default 1 GiB) bounds what a link reassembles; a larger
  message is dropped silently and the link stays up (:func:`limit_message_size`). Zenoh 1.10
  applies it loosely: after a first drop on a link, messages of 2–5× the limit were reassembled
  (10× and 64× dropped; measured), and messages around a drop may be lost. A key
  expression longer than a batch (~64 kB) makes the *sending* session panic, so keys stay short.
* All errors are ``zenoh.ZError`` (a plain ``Exception``); :func:`open_session`
  turns them into ``ValueError`` (bad configuration) or ``OSError`` (cannot
  listen / connect) so the CLI prints them as user errors.
"""

from __future__ import annotations

import argparse
import json
import re
import socket
import time
from collections.abc import Iterable
from pathlib import Path

import zenoh

__all__ = [
    "DEFAULT_PREFIX",
    "DEFAULT_PORT",
    "DEFAULT_ENDPOINT",
    "zenoh_config",
    "open_session",
    "add_zenoh_arguments",
    "session_from_args",
    "samples_key",
    "truth_key",
    "disturbance_key",
    "health_key",
    "alarm_key",
    "ack_key",
    "status_key",
    "parse_key",
    "free_tcp_port",
    "wait_for_matching",
    "query_status",
    "limit_message_size",
]

DEFAULT_PREFIX = "feedmon"
DEFAULT_PORT = 7448
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
#: a peer that only connects still listens here (ephemeral port, loopback only)
EPHEMERAL_LOOPBACK = "tcp/127.0.0.1:0"

_MODES = ("peer", "client", "router")
_ENDPOINT_RE = re.compile(r"^[a-z0-9+-]+/.+$")


def _endpoints(value: str | Iterable[str] | None, what: str) -> list[str] | None:
    if value is None:
        return None
    items = [value] if isinstance(value, str) else list(value)
    out: list[str] = []
    for item in items:
        for ep in str(item).split(","):
            ep = ep.strip()
            if not ep:
                continue
            if not _ENDPOINT_RE.match(ep):
                raise ValueError(
                    f"{what} endpoint {ep!r} is not a Zenoh locator; expected e.g. 'tcp/127.0.0.1:{DEFAULT_PORT}'"
                )
            out.append(ep)
    return out


def zenoh_config(
    *,
    mode: str | None = "peer",
    listen: str | Iterable[str] | None = None,
    connect: str | Iterable[str] | None = None,
    multicast_scouting: bool | None = False,
    config_file: str | Path | None = None,
) -> zenoh.Config:
    """Build a :class:`zenoh.Config`.

    ``mode``: ``"peer"`` (default), ``"client"`` or ``"router"``. ``listen`` /
    ``connect``: one endpoint, a comma-separated string or a list. In peer mode
    without ``listen`` the session listens on an ephemeral loopback port only
    (never on all interfaces, which is Zenoh's default). Multicast scouting is
    off unless ``multicast_scouting=True``; gossip scouting stays at Zenoh's
    default (on).

    ``config_file`` (JSON5) is the base; the keyword arguments are applied on
    top of it, except those passed as ``None`` (``mode=None`` and
    ``multicast_scouting=None`` keep the file's values; ``listen=None`` keeps the
    file's listen endpoints).

    Raises ``ValueError`` for a bad mode, endpoint or config file content and
    ``OSError`` when the config file cannot be read.
    """
    if mode is not None and mode not in _MODES:
        raise ValueError(f"Zenoh mode {mode!r} is not one of {', '.join(_MODES)}")
    listen_eps = _endpoints(listen, "listen")
    connect_eps = _endpoints(connect, "connect")
    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():
            raise FileNotFoundError(f"Zenoh config file {str(path)!r} does not exist")
        try:
            cfg = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise ValueError(f"Zenoh config file {str(path)!r} is invalid: {exc}") from None
    else:
        cfg = zenoh.Config()
        if mode is None:
            mode = "peer"
        if multicast_scouting is None:
            multicast_scouting = False
    try:
        if mode is not None:
            cfg.insert_json5("mode", json.dumps(mode))
        if multicast_scouting is not None:
            cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
        if listen_eps is None and config_file is None and mode == "peer":
            listen_eps = [EPHEMERAL_LOOPBACK]
        if listen_eps is not None:
            cfg.insert_json5("listen/endpoints", json.dumps(listen_eps))
        if connect_eps is not None:
            cfg.insert_json5("connect/endpoints", json.dumps(connect_eps))
    except zenoh.ZError as exc:  # pragma: no cover - inputs are validated above
        raise ValueError(f"invalid Zenoh configuration: {exc}") from None
    return cfg


def open_session(
    config: zenoh.Config | None = None,
    *,
    mode: str | None = "peer",
    listen: str | Iterable[str] | None = None,
    connect: str | Iterable[str] | None = None,
    multicast_scouting: bool | None = False,
    config_file: str | Path | None = None,
) -> zenoh.Session:
    """Open a Zenoh session from ``config`` or from the :func:`zenoh_config` arguments.

    Close it with ``session.close()`` (or use it as a context manager).
    Raises ``OSError`` when Zenoh cannot listen (port in use) or, in client mode,
    cannot reach any ``connect`` endpoint (its ``parameters`` names ``listen`` or ``connect``, as a
    :class:`~kernels.errors.ParameterError` does); ``ValueError`` for bad configuration.
    """
    if config is None:
        config = zenoh_config(
            mode=mode,
            listen=listen,
            connect=connect,
            multicast_scouting=multicast_scouting,
            config_file=config_file,
        )
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        msg = str(exc).split(" at /", 1)[0].strip()  # drop the Rust source location
        hint, parameters = "", ()
        if "connect" in msg.lower():
            hint, parameters = " (is the monitor or router running there? check the connect endpoints)", ("connect",)
        elif "bind" in msg.lower() or "address" in msg.lower() or "listen" in msg.lower():
            hint, parameters = (" (is another monitor already listening on that port? listen on another endpoint)",
                                ("listen",))
        err = OSError(f"cannot open Zenoh session: {msg}{hint}")
        err.parameters = parameters  # the argument to change, as on a kernels.errors.ParameterError (the CLI's hint)
        raise err from None


# ---- command line ----------------------------------------------------------------------------
def add_zenoh_arguments(parser: argparse.ArgumentParser, *, role: str = "connect") -> None:
    """Add ``--connect/--listen/--mode/--zenoh-config/--prefix`` to a sub-command.

    ``role="listen"`` (the monitor): listens on :data:`DEFAULT_ENDPOINT` unless
    ``--listen``/``--connect`` say otherwise. ``role="connect"`` (publishers,
    tools): connects to :data:`DEFAULT_ENDPOINT` as a peer unless ``--connect``
    is given, which makes it a client of that endpoint.
    Use :func:`session_from_args` to open the session.
    """
    if role not in ("listen", "connect"):
        raise ValueError(f"role must be 'listen' or 'connect', not {role!r}")
    g = parser.add_argument_group("Zenoh")
    g.add_argument(
        "--connect", metavar="ENDPOINT", action="append", default=None,
        help="Zenoh endpoint to connect to (e.g. tcp/host:7447 of a router); repeatable. "
        + ("Default: none (listen only)." if role == "listen"
           else f"Default: peer connecting to the monitor at {DEFAULT_ENDPOINT}; "
                "an explicit --connect makes this a Zenoh client."),
    )
    g.add_argument(
        "--listen", metavar="ENDPOINT", action="append", default=None,
        help="Zenoh endpoint to listen on; repeatable. "
        + (f"Default: {DEFAULT_ENDPOINT}." if role == "listen" else "Default: an ephemeral loopback port."),
    )
    g.add_argument("--mode", choices=("peer", "client"), default=None,
                   help="Zenoh mode (default: peer; client when --connect is given"
                   + (" without --listen)" if role == "listen" else ")"))
    g.add_argument("--zenoh-config", metavar="FILE", default=None,
                   help="Zenoh JSON5 config file used as the base configuration")
    g.add_argument("--multicast", action="store_true",
                   help="enable Zenoh multicast scouting (off by default)")
    g.add_argument("--prefix", default=DEFAULT_PREFIX,
                   help=f"key expression prefix (default: {DEFAULT_PREFIX})")
    parser.set_defaults(_zenoh_role=role)


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """The Zenoh configuration described by the :func:`add_zenoh_arguments` options."""
    role = getattr(args, "_zenoh_role", "connect")
    connect, listen, mode = args.connect, args.listen, args.mode
    cfg_file = getattr(args, "zenoh_config", None)
    multicast = True if getattr(args, "multicast", False) else (None if cfg_file else False)
    if cfg_file is None:
        if role == "listen":
            if listen is None and connect is None:
                listen = [DEFAULT_ENDPOINT]
            if mode is None:
                mode = "client" if (connect and not listen) else "peer"
        else:
            if mode is None:
                mode = "client" if connect else "peer"
            if connect is None:
                connect = [DEFAULT_ENDPOINT]
        if mode == "client" and not connect:
            raise ValueError("--mode client needs --connect ENDPOINT")
        if mode == "client":
            listen = None
    return zenoh_config(mode=mode, listen=listen, connect=connect, multicast_scouting=multicast, config_file=cfg_file)


def limit_message_size(config: zenoh.Config, nbytes: int) -> zenoh.Config:
    """Make the links of sessions opened with ``config`` drop every received message larger than
    ``nbytes`` (``transport/link/rx/max_message_size``; Zenoh's default is 1 GiB): such a message is
    never reassembled in memory and never reaches a callback. Zenoh does not say it dropped one, and
    Zenoh 1.10 enforces it loosely (after a first drop on a link, up to ~5× ``nbytes`` was seen
    reassembled), so this is a memory backstop: give callbacks an exact, smaller limit of their own
    and count refusals there. Returns ``config``."""
    if not 1 <= int(nbytes) <= 1 << 32:
        raise ValueError(f"message size limit must be 1 … 2**32 bytes, got {nbytes}")
    config.insert_json5("transport/link/rx/max_message_size", json.dumps(int(nbytes)))
    return config


def session_from_args(args: argparse.Namespace) -> zenoh.Session:
    """Open the session described by the :func:`add_zenoh_arguments` options."""
    return open_session(config_from_args(args))


def describe_config(config: zenoh.Config) -> dict:
    """``{"mode", "listen", "connect"}`` as the configuration says (what a session opened from it does)."""
    def get(key, default):
        try:
            value = json.loads(config.get_json(key))
        except Exception:  # noqa: BLE001 - a key absent from the config
            return default
        return default if value is None else value

    listen = get("listen/endpoints", [])
    connect = get("connect/endpoints", [])
    if isinstance(listen, dict):  # per-mode endpoint lists
        listen = listen.get(get("mode", "peer"), [])
    if isinstance(connect, dict):
        connect = connect.get(get("mode", "peer"), [])
    return {"mode": get("mode", "peer"), "listen": list(listen), "connect": list(connect)}





# ---- key expressions -------------------------------------------------------------------------
_BAD_CHUNK = re.compile(r"[/*$?#\s]")


def _chunk(value: str, what: str, *, wildcard: bool) -> str:
    value = str(value)
    if wildcard and value in ("*", "**"):
        return value
    if not value or _BAD_CHUNK.search(value):
        raise ValueError(
            f"{what} {value!r} cannot be used in a key expression "
            "(must be non-empty without '/', '*', '$', '?', '#' or spaces)"
        )
    return value


def _prefix(prefix: str) -> str:
    prefix = str(prefix).strip("/")
    if not prefix:
        raise ValueError("key expression prefix must not be empty")
    for part in prefix.split("/"):
        _chunk(part, "prefix part", wildcard=False)
    return prefix


def _axis_key(prefix: str, machine: str, axis: str, kind: str) -> str:
    return f"{_prefix(prefix)}/{_chunk(machine, 'machine', wildcard=True)}/{_chunk(axis, 'axis', wildcard=True)}/{kind}"


def samples_key(prefix: str = DEFAULT_PREFIX, machine: str = "*", axis: str = "*") -> str:
    """``<prefix>/<machine>/<axis>/samples`` (``*`` for machine/axis gives a wildcard)."""
    return _axis_key(prefix, machine, axis, "samples")


def truth_key(prefix: str = DEFAULT_PREFIX, machine: str = "*", axis: str = "*") -> str:
    """``<prefix>/<machine>/<axis>/truth`` (ground truth published by ``feedmon replay``)."""
    return _axis_key(prefix, machine, axis, "truth")


def disturbance_key(prefix: str = DEFAULT_PREFIX, machine: str = "*", axis: str = "*") -> str:
    """``<prefix>/<machine>/<axis>/disturbance`` (the monitor's EstimateBlocks)."""
    return _axis_key(prefix, machine, axis, "disturbance")


def health_key(prefix: str = DEFAULT_PREFIX, machine: str = "*", axis: str = "*") -> str:
    """``<prefix>/<machine>/<axis>/health`` (the monitor's health reports, :class:`feedio.schema.Health`)."""
    return _axis_key(prefix, machine, axis, "health")


def alarm_key(prefix: str = DEFAULT_PREFIX, machine: str = "*", axis: str = "*") -> str:
    """``<prefix>/<machine>/<axis>/alarm`` (the process monitors' alarms, :class:`feedio.schema.AlarmEvent`)."""
    return _axis_key(prefix, machine, axis, "alarm")


def ack_key(prefix: str = DEFAULT_PREFIX, machine: str = "*", axis: str = "*") -> str:
    """``<prefix>/<machine>/<axis>/ack``: an operator's false-alarm acknowledgement (JSON ``{"monitor": …}``)."""
    return _axis_key(prefix, machine, axis, "ack")


def status_key(prefix: str = DEFAULT_PREFIX) -> str:
    """``<prefix>/monitor/status`` (queryable answering the monitor status as JSON)."""
    return f"{_prefix(prefix)}/monitor/status"


def parse_key(key: str | zenoh.KeyExpr, prefix: str = DEFAULT_PREFIX) -> tuple[str, str, str]:
    """``(machine, axis, kind)`` of a concrete ``<prefix>/<machine>/<axis>/<kind>`` key."""
    key = str(key)
    p = _prefix(prefix) + "/"
    if not key.startswith(p):
        raise ValueError(f"key {key!r} does not start with prefix {p!r}")
    parts = key[len(p):].split("/")
    if len(parts) != 3:
        raise ValueError(f"key {key!r} is not of the form {p}<machine>/<axis>/<kind>")
    return parts[0], parts[1], parts[2]


# ---- helpers ---------------------------------------------------------------------------------
def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (for tests: there is a small race)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def wait_for_matching(publisher: zenoh.Publisher, timeout: float) -> bool:
    """Wait until ``publisher`` has a matching subscriber; True if it has one within ``timeout`` s."""
    deadline = time.monotonic() + max(0.0, timeout)
    while True:
        if publisher.matching_status.matching:
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)


def query_status(session, prefix: str = "feedmon", timeout: float = 5.0) -> list[dict]:
    """Status dicts of every monitor answering within ``timeout`` s (retries: declarations take a moment)."""
    from feedio.transport import status_key

    key = status_key(prefix)
    deadline = time.monotonic() + max(0.0, timeout)
    while True:
        left = max(0.1, min(2.0, deadline - time.monotonic()))
        out = []
        for reply in session.get(key, timeout=left):
            if reply.ok is not None:
                try:
                    out.append(json.loads(reply.ok.payload.to_bytes()))
                except ValueError:
                    out.append({"error": "unparseable status reply", "key": str(reply.ok.key_expr)})
        if out or time.monotonic() >= deadline:
            return out
        time.sleep(0.1)
