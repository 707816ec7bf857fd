"""The LinuxCNC bridge's configuration: which sampler column is which HAL pin, and what it means.

One TOML file (``feedmon bridge linuxcnc --config FILE``), one msgspec Struct per table; decoding
checks every key, type and range, and an error names the file, the key and the allowed range.
The cross-field rules (:meth:`BridgeConfig.check`) name the pin concerned::

    machine = "mill"
    servo_period = 0.001               # s, the period of the thread sampler.N runs in
    sampler = 0                        # the channel N of `loadrt sampler`: sampler.N
    counter = "threadtest.0.count"     # the column counting servo cycles: seq and t come from it
    columns = ["threadtest.0.count", "joint.0.vel-cmd", "joint.0.motor-pos-fb", "pid.x.output",
               "motion.program-line"]  # sampler.N.pin.0, .1, …: the HAL pin (or signal) feeding each
    program_line = "motion.program-line"

    [axes.X]
    v_ref = "joint.0.vel-cmd"
    position = "joint.0.motor-pos-fb"  # or v_meas = "…"
    u = "pid.x.output"
    length_scale = 0.001               # m per machine unit (mm)

    [axes.X.links]                     # the way back: this axis' pins of the bridge's HAL component
    alarm = "feedmon-alarm"            # linked to this signal (e.g. net feedmon-alarm => motion.feed-hold)

Every column of the sampler is named in ``columns`` (a column the bridge does not map is allowed,
e.g. a truth logged alongside); every HAL name an axis uses is one of ``columns``.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Annotated, Literal

import msgspec

from feedio.limits import MAX_CONFIG_BYTES, NAME_PATTERN, FileTooLarge, explain, read_capped
from feedio.schema import check_name

__all__ = ["AxisConfig", "Publish", "HalSide", "BridgeConfig", "load_config", "PIN_FIELDS", "LINK_PINS",
           "MAX_CONFIG_BYTES", "ConfigError"]

#: a HAL pin or signal name (halcmd allows letters, digits and ``. _ - :``; at most 47 characters)
_HAL_NAME = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.:-]{1,47}$")]
_Scale = Annotated[float, msgspec.Meta(gt=0.0, le=1e9)]
#: the axis fields that name a column, and the sampler types each accepts
PIN_FIELDS = {"v_ref": "f", "v_meas": "f", "position": "f", "u": "f", "current": "f",
              "spindle_revs": "f", "spindle_speed": "f"}
#: the way-back pins of one axis (``<component>.<axis>.<pin>``) and their HAL types
LINK_PINS = {"force": "float", "force-sigma": "float", "health": "s32", "alarm": "bit", "valid": "bit",
             "sample": "u32"}


class ConfigError(ValueError):
    """The bridge configuration is wrong (the message names the file, key or pin)."""


class AxisConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """One axis: the columns of its :class:`~feedio.schema.SampleBlock` and their scales."""

    form: Literal["velocity-loop", "force-input"] | None = None  # default: force-input when u is given
    v_ref: _HAL_NAME | None = None  # velocity reference, machine units/s
    v_meas: _HAL_NAME | None = None  # measured velocity, machine units/s
    position: _HAL_NAME | None = None  # measured position, machine units (without v_meas: its backward difference)
    u: _HAL_NAME | None = None  # force (or torque-producing) command, × force_scale = N
    current: _HAL_NAME | None = None  # motor current, × current_scale = A
    spindle_revs: _HAL_NAME | None = None  # spindle revolutions (e.g. spindle.0.revs) → spindle_angle, rad
    spindle_speed: _HAL_NAME | None = None  # spindle speed (e.g. spindle.0.speed-in) → spindle_rpm
    spindle_speed_unit: Literal["rpm", "rps"] = "rpm"  # LinuxCNC's spindle.N.speed-in is rps
    length_scale: _Scale = 1.0  # m per machine unit (1 for m, 0.001 for mm)
    force_scale: _Scale = 1.0  # N per unit of u
    current_scale: _Scale = 1.0  # A per unit of current
    links: dict[str, _HAL_NAME] = {}  # way-back pin (LINK_PINS) → HAL signal it drives

    @property
    def resolved_form(self) -> str:
        return self.form or ("force-input" if self.u is not None else "velocity-loop")

    def pins(self) -> dict[str, str]:
        """``{field: column}`` of the fields that name a column."""
        return {f: getattr(self, f) for f in PIN_FIELDS if getattr(self, f) is not None}


class Publish(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """How samples leave: ``block`` samples per message at most (1: every sample at once); a shorter
    block goes out when its first sample has waited ``max_delay`` s (latency bound)."""

    block: Annotated[int, msgspec.Meta(ge=1, le=10_000)] = 1
    max_delay: Annotated[float, msgspec.Meta(ge=0.0, le=10.0)] = 0.01


class HalSide(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The HAL helper: the Python LinuxCNC's ``hal`` module is built for, the user it runs as (when
    the bridge runs as root: HAL refuses root), how often it polls the FIFO (s), the name of the
    way-back component, how long the way-back pins stay ``valid`` without a new estimate (s), and
    the wait between two attempts to attach to HAL (s, while LinuxCNC is not running)."""

    python: Annotated[str, msgspec.Meta(min_length=1, max_length=4096)] = "/usr/bin/python3"
    user: Annotated[str, msgspec.Meta(pattern=r"^[a-z_][a-z0-9_-]{0,31}$")] | None = None
    halcmd: Annotated[str, msgspec.Meta(min_length=1, max_length=4096)] = "halcmd"
    poll: Annotated[float, msgspec.Meta(ge=1e-4, le=0.1)] = 0.0005
    component: Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_-]{1,32}$")] = "feedmon"
    stale_after: Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)] = 0.5
    retry: Annotated[float, msgspec.Meta(ge=0.05, le=60.0)] = 0.5


class BridgeConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The whole file (module docstring)."""

    machine: Annotated[str, msgspec.Meta(pattern=NAME_PATTERN)]
    servo_period: Annotated[float, msgspec.Meta(ge=1e-5, le=1.0)]
    sampler: Annotated[int, msgspec.Meta(ge=0, le=7)] = 0
    counter: _HAL_NAME
    columns: Annotated[list[_HAL_NAME], msgspec.Meta(min_length=2, max_length=20)]
    program_line: _HAL_NAME | None = None
    tool: _HAL_NAME | None = None
    axes: Annotated[dict[str, AxisConfig], msgspec.Meta(min_length=1, max_length=16)]
    publish: Publish = Publish()
    hal: HalSide = HalSide()

    def column(self, name: str) -> int:
        return self.columns.index(name)

    def context(self) -> dict[str, str]:
        """``{program_line|tool: column}`` of the context columns given."""
        return {k: getattr(self, k) for k in ("program_line", "tool") if getattr(self, k) is not None}

    def check(self, where: str = "config") -> BridgeConfig:
        """The rules across keys; :class:`ConfigError` naming the key and the pin."""
        dup = sorted({c for c in self.columns if self.columns.count(c) > 1})
        if dup:
            raise ConfigError(f"{where}: columns name {', '.join(dup)} twice; each sampler column is one pin")
        known = set(self.columns)
        for key, name in [("counter", self.counter), *self.context().items()]:
            if name not in known:
                raise ConfigError(f"{where}: {key} = {name!r} is not one of the sampler's columns; add it to columns "
                                  "(and net it to the sampler pin at that position)")
        for axis, ax in self.axes.items():
            try:
                check_name(axis, "axis")
            except ValueError as exc:
                raise ConfigError(f"{where}: [axes.{axis}]: {exc}") from None
            for field, name in ax.pins().items():
                if name not in known:
                    raise ConfigError(f"{where}: axes.{axis}.{field} = {name!r} is not one of the sampler's columns; "
                                      "add it to columns (and net it to the sampler pin at that position)")
            if ax.v_meas is None and ax.position is None:
                raise ConfigError(f"{where}: axes.{axis}: give the measured velocity as v_meas, or a position to "
                                  "differentiate")
            need = "u" if ax.resolved_form == "force-input" else "v_ref"
            if getattr(ax, need) is None:
                raise ConfigError(f"{where}: axes.{axis}: the {ax.resolved_form} form needs {need}")
            for pin in ax.links:
                if pin not in LINK_PINS:
                    raise ConfigError(f"{where}: axes.{axis}.links.{pin}: the bridge has no such pin; its pins are "
                                      f"{', '.join(LINK_PINS)}")
        signals = [s for ax in self.axes.values() for s in ax.links.values()]
        dup = sorted({s for s in signals if signals.count(s) > 1})
        if dup:
            raise ConfigError(f"{where}: links drive signal {', '.join(dup)} from two pins; a signal has one writer")
        if not math.isfinite(self.servo_period):
            raise ConfigError(f"{where}: servo_period must be finite")
        return self


def _explain(exc: msgspec.ValidationError) -> str:
    """``key <path>: <message>``, with the allowed range of a numeric key or the known keys of a table."""
    key, msg = explain(exc, BridgeConfig)
    return f"key {key}: {msg}"


def load_config(path: str | Path) -> BridgeConfig:
    """The checked configuration of ``path``; ``ConfigError`` (a ValueError) naming the file and key,
    ``FileNotFoundError`` when it does not exist."""
    path = Path(path)
    try:
        doc = tomllib.loads(read_capped(path, MAX_CONFIG_BYTES, "bridge config file").decode("utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"bridge config file {str(path)!r} does not exist") from None
    except FileTooLarge as exc:
        raise ConfigError(str(exc)) from None
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, RecursionError) as exc:
        raise ConfigError(f"config file {path}: not valid UTF-8 TOML ({exc})") from None
    try:
        cfg = msgspec.convert(doc, BridgeConfig)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"config file {path}: {_explain(exc)}") from None
    return cfg.check(f"config file {path}")
