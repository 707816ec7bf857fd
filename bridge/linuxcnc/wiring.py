"""Is the sampler wired as the configuration says? Checked with ``halcmd`` before the first sample.

``halcmd -s show pin sampler.N.`` tells which signal feeds each ``sampler.N.pin.K``, ``halcmd -s
show sig`` which pin writes each signal, ``halcmd -s show thread`` each thread's period (ns) and
functions. A configuration column matches ``sampler.N.pin.K`` when it names that signal, its writer or any pin on it (a pin reading the same signal samples the same value). Each mismatch is a :class:`~bridge.linuxcnc.config.ConfigError` naming the sampler pin,
what HAL has there and what the configuration says.
"""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass

from .config import PIN_FIELDS, BridgeConfig, ConfigError

__all__ = ["Wiring", "read_wiring", "parse_pins", "parse_signals", "parse_threads", "check_wiring"]

#: what a type character of a sampler ``cfg`` string is called
TYPE_NAMES = {"f": "float", "b": "bit", "s": "s32", "u": "u32"}


@dataclass(frozen=True)
class Wiring:
    """``pins``: sampler pin → signal (None: not connected); ``signals``: signal → (writing pin or
    None, every pin on it); ``threads``: thread → (period in ns, its functions in order)."""

    pins: dict[str, str | None]
    signals: dict[str, tuple[str | None, list[str]]]
    threads: dict[str, tuple[int, list[str]]]

    def driver(self, sig: str | None) -> str | None:
        return self.signals.get(sig, (None, []))[0] if sig else None


def parse_pins(text: str) -> dict[str, str | None]:
    """``halcmd -s show pin``: ``owner type dir value name [<== signal]`` → ``{name: signal}``."""
    out: dict[str, str | None] = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) >= 5:
            out[parts[4]] = parts[6] if len(parts) >= 7 and parts[5] in ("<==", "==>", "<=>") else None
    return out


def parse_signals(text: str) -> dict[str, tuple[str | None, list[str]]]:
    """``halcmd -s show sig``: ``type value name (==> reader | <== writer | <=> io)*`` →
    ``{name: (writer, pins)}``."""
    out: dict[str, tuple[str | None, list[str]]] = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) >= 3:
            arrows = list(zip(parts[3::2], parts[4::2]))
            out[parts[2]] = (next((pin for arrow, pin in arrows if arrow == "<=="), None), [p for _, p in arrows])
    return out


def parse_threads(text: str) -> dict[str, tuple[int, list[str]]]:
    """``halcmd -s show thread``: ``period fp name time max-time funct…`` → ``{name: (period_ns, functs)}``."""
    out = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) >= 5 and parts[0].isdigit():
            out[parts[2]] = (int(parts[0]), parts[5:])
    return out


def _halcmd(cfg: BridgeConfig, *args: str) -> str:
    """``halcmd -s ARGS``, as ``[hal] user`` when this process is root: should HAL be gone by then, the
    ``halcmd`` would create an empty HAL, and one owned by root would lock LinuxCNC's next start out."""
    halcmd = cfg.hal.halcmd
    cmd = [halcmd, "-s", *args]
    if cfg.hal.user is not None and os.geteuid() == 0:
        cmd = ["runuser", "-u", cfg.hal.user, "--", *cmd]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=20)
    except FileNotFoundError:
        raise OSError(f"{halcmd} not found: install LinuxCNC (apt-get install linuxcnc-uspace) or set "
                      "[hal] halcmd") from None
    except subprocess.TimeoutExpired:
        raise OSError(f"{halcmd} {' '.join(args)} did not answer within 20 s") from None
    if res.returncode != 0:
        raise OSError(f"{halcmd} {' '.join(args)} failed: {res.stderr.strip() or res.stdout.strip()}")
    return res.stdout


def read_wiring(cfg: BridgeConfig) -> Wiring:
    """The wiring of ``sampler.<cfg.sampler>`` as HAL has it now."""
    return Wiring(parse_pins(_halcmd(cfg, "show", "pin", f"sampler.{cfg.sampler}.")),
                  parse_signals(_halcmd(cfg, "show", "sig")), parse_threads(_halcmd(cfg, "show", "thread")))


def _types_needed(cfg: BridgeConfig) -> list[tuple[str, str, str]]:
    """``[(column, allowed type characters, what uses it)]``."""
    need = [(cfg.counter, "us", "counter")]
    need += [(col, "us", key) for key, col in cfg.context().items()]
    for axis, ax in cfg.axes.items():
        need += [(col, PIN_FIELDS[field], f"axes.{axis}.{field}") for field, col in ax.pins().items()]
    return need


def check_wiring(cfg: BridgeConfig, types: str, wiring: Wiring) -> None:
    """``types``: the FIFO's column types (``cfg=`` of ``loadrt sampler``, e.g. ``"uffffs"``)."""
    n = cfg.sampler
    for k in range(max(len(types), len(cfg.columns))):
        pin = f"sampler.{n}.pin.{k}"
        sig = wiring.pins.get(pin)
        fed = "nothing (not connected)" if sig is None else \
            f"signal {sig}" + (f" (written by {wiring.driver(sig)})" if wiring.driver(sig) else " (no writer)")
        if k >= len(cfg.columns):
            raise ConfigError(f"{pin} (fed by {fed}) is not in the config's columns, which list {len(cfg.columns)}: "
                              f"sampler.{n} was loaded with cfg={types}; add its name at position {k}")
        name = cfg.columns[k]
        if k >= len(types):
            raise ConfigError(f"the config's column {k}, {name}, has no sampler pin: sampler.{n} was loaded with "
                              f"cfg={types} ({len(types)} columns); add a column to its cfg and net {name} to {pin}")
        if sig is None or name != sig and name not in wiring.signals.get(sig, (None, []))[1]:
            raise ConfigError(f"{pin} is fed by {fed}, but the config's column {k} is {name}: net {name} to {pin}, "
                              "or list the columns in the sampler's pin order")
    for col, allowed, what in _types_needed(cfg):
        t = types[cfg.column(col)]
        if t.lower() not in allowed:
            raise ConfigError(f"{col} ({what}) is sampled as {TYPE_NAMES.get(t.lower(), t)} by sampler.{n}.pin."
                              f"{cfg.column(col)}; it needs {' or '.join(TYPE_NAMES[a] for a in allowed)}")
    _check_thread(cfg, wiring)


def _check_thread(cfg: BridgeConfig, wiring: Wiring) -> None:
    funct = f"sampler.{cfg.sampler}"
    thread = next((name for name, (_, functs) in wiring.threads.items() if funct in functs), None)
    if thread is None:
        raise ConfigError(f"{funct} is in no HAL thread: add 'addf {funct} servo-thread' to the HAL file")
    period_ns, functs = wiring.threads[thread]
    if round(cfg.servo_period * 1e9) != period_ns:
        raise ConfigError(f"servo_period = {cfg.servo_period:g} s in the config, but {funct} runs in {thread} every "
                          f"{period_ns * 1e-9:g} s ({period_ns} ns): set servo_period = {period_ns * 1e-9:g}")
    driver = wiring.driver(wiring.pins.get(f"{funct}.pin.{cfg.column(cfg.counter)}"))
    if driver and driver.startswith("threadtest.") and driver.endswith(".count"):
        inc = driver[:-len("count")] + "increment"
        if inc not in functs:
            raise ConfigError(f"the counter {driver} must count the cycles of {thread}, where {funct} runs: "
                              f"add 'addf {inc} {thread}'")
