"""The ``feedmon run`` configuration: one msgspec Struct for the ``--config`` file and the options.

The TOML file has a ``[run]`` table (the long option names, dashes as underscores) with a
``[run.limits]`` sub-table (:class:`feedio.limits.InputLimits`) and optional ``[run.tracker]``,
``[run.adaptation]``, ``[run.health]`` sub-tables that override the model files' online settings
for every axis (:mod:`monitor.online_settings`; a key left out keeps the model file's value)::

    [run]
    model = ["/var/lib/feedmon/models/axis-x.model.toml"]
    mcap = "/var/log/feedmon"

    [run.limits]
    max_message_bytes = 4_194_304

Decoding checks every key, type and range; an error names the file, the key (``run.limits.queue_bytes``)
and the allowed range. Options given on the command line override the file, key by key, and are
checked against the same ranges (an error then names the option). Relative paths in the file are
relative to the file's directory. Further top-level tables (e.g. tracker overrides) go next to
``run`` in :class:`ConfigFile`.
"""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec

from feedio.limits import MAX_CONFIG_BYTES, InputLimits, explain, read_capped
from monitor import online_settings as OS
from monitor.input_health import InputHealthSettings
from monitor.process_monitor.settings import MonitorSettings
from monitor.sinks.child import Priority

__all__ = ["RunConfig", "ConfigFile", "load_config_file", "run_config_from_args", "parse_limit_option",
           "monitor_settings_from_args"]

#: keys whose values are paths (relative to the config file's directory)
PATH_KEYS = ("model", "mcap", "rrd", "state_dir", "zenoh_config")
#: a larger file is refused before it is parsed


class RunConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Everything ``feedmon run`` is told, from the ``[run]`` table and the command line."""

    model: list[str] = []
    mcap: str | None = None
    rotate_mb: Annotated[float, msgspec.Meta(gt=0.0, le=1e6)] | None = None
    rotate_minutes: Annotated[float, msgspec.Meta(gt=0.0, le=1e6)] | None = None
    rrd: str | None = None
    serve_rerun: Annotated[int, msgspec.Meta(ge=1, le=65535)] | None = None
    record_truth: bool = False
    sink_priority: Priority = "low"  # the sink processes: nice 10, or SCHED_IDLE (monitor.sinks.child)
    state_dir: str | None = None
    fresh: bool = False
    drain_seconds: Annotated[float, msgspec.Meta(ge=0.0, le=3600.0)] = 30.0
    # the sink processes (monitor.sinks.child): start, stall detection, finishing at stop
    sink_start_seconds: Annotated[float, msgspec.Meta(ge=5.0, le=3600.0)] = 60.0
    sink_stall_seconds: Annotated[float, msgspec.Meta(ge=2.0, le=3600.0)] = 10.0
    sink_close_seconds: Annotated[float, msgspec.Meta(ge=1.0, le=3600.0)] = 30.0
    # MiB an output directory (--mcap, --rrd) must have free at start; below it when a new file opens: degraded
    min_free_mb: Annotated[float, msgspec.Meta(ge=0.0, le=1e7)] = 64.0
    jobs: Annotated[int, msgspec.Meta(ge=1, le=1024)] | None = None  # offline: processes (None: one per core)
    listen: list[str] | None = None
    connect: list[str] | None = None
    mode: Literal["peer", "client"] | None = None
    zenoh_config: str | None = None
    multicast: bool = False
    prefix: Annotated[str, msgspec.Meta(min_length=1, max_length=200)] = "feedmon"
    limits: InputLimits = InputLimits()
    # online settings for every axis instead of the model files' ([run.tracker], [run.adaptation], [run.health])
    tracker: OS.TrackerOverride = OS.TrackerOverride()
    adaptation: OS.AdaptationOverride = OS.AdaptationOverride()
    health: OS.HealthOverride = OS.HealthOverride()
    # thresholds of the input-health verdict ([run.input_health]; monitor.input_health)
    input_health: InputHealthSettings = InputHealthSettings()


class ConfigFile(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """The whole ``--config`` file: one table per concern."""

    run: RunConfig = RunConfig()
    #: the process monitors ([monitors]; monitor.process_monitor, docs/process-monitoring.md)
    monitors: MonitorSettings = MonitorSettings()


# ---- the file ----------------------------------------------------------------------------------
def _as_list(value: Any) -> Any:
    return [value] if isinstance(value, str) else value


def load_config_file(path: str | Path) -> ConfigFile:
    """The decoded file, its paths made absolute.

    Raises ``FileNotFoundError``, or ``ValueError`` naming the file, the key and the allowed range
    (also for a file over :data:`MAX_CONFIG_BYTES` or nested too deeply to parse).
    """
    path = Path(path)
    try:
        doc = tomllib.loads(read_capped(path, MAX_CONFIG_BYTES, "config file").decode("utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"config file {str(path)!r} does not exist") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"config file {path}: not UTF-8 text ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"config file {path}: not valid TOML ({exc})") from None
    except RecursionError:
        raise ValueError(f"config file {path}: nested too deeply") from None
    run = doc.get("run")
    if isinstance(run, dict):
        base = path.resolve().parent
        for key in ("model", "listen", "connect"):
            if key in run:
                run[key] = _as_list(run[key])
        for key in PATH_KEYS:
            v = run.get(key)
            if isinstance(v, str):
                run[key] = str(base / v)
            elif isinstance(v, list):
                run[key] = [str(base / x) if isinstance(x, str) else x for x in v]
    env = (doc.get("monitors") or {}).get("envelope") if isinstance(doc.get("monitors"), dict) else None
    if isinstance(env, dict) and isinstance(env.get("reference"), (str, list)):  # paths relative to the file
        base = path.resolve().parent
        env["reference"] = [str(base / x) if isinstance(x, str) else x for x in _as_list(env["reference"])]
    wear = (doc.get("monitors") or {}).get("wear") if isinstance(doc.get("monitors"), dict) else None
    if isinstance(wear, dict) and isinstance(wear.get("history"), str):  # relative to the file
        wear["history"] = str(path.resolve().parent / wear["history"])
    try:
        return msgspec.convert(doc, ConfigFile)
    except msgspec.ValidationError as exc:
        key, msg = explain(exc, ConfigFile)
        hint = " (the options of feedmon run go in a [run] table)" if key == "(top level)" else ""
        raise ValueError(f"config file {path}: key {key}: {msg}{hint}") from None


# ---- the command line --------------------------------------------------------------------------
def parse_limit_option(text: str) -> tuple[str, Any]:
    """``NAME=VALUE`` of ``--limit`` (VALUE a JSON number, ``_`` allowed as in TOML)."""
    name, sep, value = text.partition("=")
    name = name.strip().replace("-", "_")
    if not sep or not name:
        raise ValueError(f"--limit {text!r}: expected NAME=VALUE, e.g. --limit max_message_bytes=1048576")
    try:
        parsed = json.loads(value.strip().replace("_", ""))
    except ValueError:
        raise ValueError(f"--limit {text!r}: {value!r} is not a number") from None
    if not isinstance(parsed, int | float) or isinstance(parsed, bool):
        raise ValueError(f"--limit {text!r}: {value!r} is not a number")
    return name, parsed


def run_config_from_args(args: argparse.Namespace) -> RunConfig:
    """The :class:`RunConfig` of ``feedmon run``: the ``--config`` file (if any), then the options
    given on the command line on top (``None`` / absent flags do not override)."""
    if getattr(args, "config", None):
        cfg = load_config_file(args.config).run
    else:
        cfg = RunConfig()
    cli: dict[str, Any] = {}
    for name in RunConfig.__struct_fields__:
        if name in ("limits", "tracker", "adaptation", "health", "input_health") or not hasattr(args, name):
            continue
        value = getattr(args, name)
        if value is None or value is False:  # not given (flags cannot switch off what the file switches on)
            continue
        cli[name] = value
    for name, value in cli.items():  # each option against the same ranges as the file's key
        try:
            msgspec.convert({name: value}, RunConfig)
        except msgspec.ValidationError as exc:
            _, msg = explain(exc, RunConfig)
            raise ValueError(f"option --{name.replace('_', '-')}: {msg}") from None
    given: dict[str, tuple[Any, str]] = {}  # limit -> (value, option that gave it)
    if getattr(args, "queue", None) is not None:
        given["queue_messages"] = (args.queue, "--queue")
    for text in getattr(args, "limit", None) or []:
        k, v = parse_limit_option(text)
        given[k] = (v, f"--limit {k}")
    for k, (v, opt) in given.items():
        if k not in InputLimits.__struct_fields__:
            raise ValueError(f"{opt}: unknown limit; known: {', '.join(InputLimits.__struct_fields__)}")
        try:
            msgspec.convert({k: v}, InputLimits)
        except msgspec.ValidationError as exc:
            raise ValueError(f"option {opt}: {explain(exc, InputLimits)[1]}") from None
    try:
        merged = msgspec.convert({**msgspec.to_builtins(cfg.limits), **{k: v for k, (v, _) in given.items()}},
                                 InputLimits)
    except msgspec.ValidationError as exc:  # a cross-field rule (queue_bytes >= max_message_bytes)
        where = f"config file {args.config} and options" if getattr(args, "config", None) else "options"
        raise ValueError(f"limits ({where}): {explain(exc, InputLimits)[1]}") from None
    return msgspec.structs.replace(cfg, limits=merged, **cli)


def monitor_settings_from_args(args: argparse.Namespace) -> MonitorSettings:
    """The ``[monitors]`` table of ``--config`` with ``--monitors`` (switch them on), ``--reference FILE``
    (add a reference envelope) and ``--wear-history FILE`` (the wear history; both switch them on) on top."""
    ms = load_config_file(args.config).monitors if getattr(args, "config", None) else MonitorSettings()
    refs = getattr(args, "reference", None) or []
    wear = getattr(args, "wear_history", None)
    if getattr(args, "monitors", False) or refs or wear:
        env = msgspec.structs.replace(ms.envelope, reference=[*ms.envelope.reference, *refs])
        ms = msgspec.structs.replace(ms, enabled=True, envelope=env)
    if wear:
        ms = msgspec.structs.replace(ms, wear=msgspec.structs.replace(ms.wear, history=wear))
    return ms
