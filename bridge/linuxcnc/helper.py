"""The bridge's end of the HAL helper (:mod:`bridge.linuxcnc.halio`, a child process).

Why a child process: LinuxCNC's ``hal`` module is a C extension built for the system Python
(Debian 12: ``/usr/bin/python3``, 3.11, pinned below 3.12 by the package), while feedmon runs in
its own virtual environment, under any Python ≥ 3.11. ``halsampler`` would serve the input from
any Python, but it polls its FIFO every 10 ms, block-buffers its output into a pipe and prints
floats with six decimals; and the way back needs output pins, which only a HAL component can own.
So one small helper under the system Python does both — it reads the FIFO every ``poll`` seconds
and owns the pins — and the bridge keeps everything else (mapping, Zenoh, MCAP) in its own
environment. When the bridge runs as root, the helper runs as ``[hal] user`` (HAL refuses root,
and LinuxCNC's shutdown must be able to signal it).
"""

from __future__ import annotations

import json
import os
import select
import signal
import struct
import subprocess
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import BridgeConfig
from .halio import DATA_HEAD

__all__ = ["HalHelper", "HalUnavailable", "HalError", "Hello", "Frame"]

_HEAD = struct.Struct("<IB")
#: helper exit codes that mean "HAL is not (or no longer) there": wait and attach again
WAIT_CODES = (4, 5)
MAX_FRAME = 1 << 26


class HalError(OSError):
    """The helper failed for a reason waiting will not cure (message from the helper)."""


class HalUnavailable(HalError):
    """HAL or the sampler's FIFO is not there (yet, or any more): try again later."""


@dataclass(frozen=True)
class Hello:
    types: str  # the FIFO's column types, e.g. "uffffu"
    maxdepth: int  # FIFO depth (samples)
    overruns: int  # the FIFO's overrun count when attached
    stale: int  # samples the FIFO held when attached (written while nobody read it), discarded
    session: int  # HAL's shared-memory id: changes when HAL restarts
    pid: int


@dataclass(frozen=True)
class Frame:
    t_read: float  # CLOCK_MONOTONIC (s) when the rows were read
    overruns: int  # the FIFO's overrun count then
    rows: np.ndarray  # (n, columns) float64


class HalHelper:
    """Start, read and command one helper. ``pins``: ``[(name, hal type)]`` of the way-back
    component, ``links``: ``{pin: signal}``."""

    def __init__(self, cfg: BridgeConfig, pins: list[tuple[str, str]], links: dict[str, str]) -> None:
        spec = {"component": cfg.hal.component, "sampler": cfg.sampler, "pins": pins, "links": links,
                "poll": cfg.hal.poll}
        src = Path(__file__).with_name("halio.py").read_text(encoding="utf-8")
        cmd = [cfg.hal.python, "-I", "-c", src, json.dumps(spec)]
        if cfg.hal.user is not None and os.geteuid() == 0:
            cmd = ["runuser", "-u", cfg.hal.user, "--", *cmd]
        try:
            self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                         start_new_session=True)
        except FileNotFoundError as exc:
            raise HalError(f"cannot start the HAL helper: {exc.filename} not found ([hal] python: the Python "
                           "LinuxCNC's hal module is built for)") from None
        self._buf = bytearray()
        self._lock = threading.Lock()
        self._stderr: list[bytes] = []
        threading.Thread(target=self._drain_stderr, daemon=True).start()
        self.hello: Hello | None = None

    def _drain_stderr(self) -> None:
        for line in self.proc.stderr:
            self._stderr = (self._stderr + [line])[-20:]

    def start(self, timeout: float = 20.0) -> Hello:
        """Wait for the helper's hello (:class:`HalUnavailable` when HAL is not running)."""
        item = self.read(timeout)
        if isinstance(item, Hello):
            self.hello = item
            return item
        self.close()
        raise HalError("the HAL helper did not say hello within "
                       f"{timeout:g} s{self._tail()}")

    def _tail(self) -> str:
        text = b"".join(self._stderr).decode(errors="replace").strip()
        return f" (its stderr: {text[-800:]})" if text else ""

    def read(self, timeout: float) -> Hello | Frame | None:
        """The next frame (None: nothing within ``timeout`` s). Raises :class:`HalUnavailable` /
        :class:`HalError` when the helper reports an error or ends."""
        out = self._next()
        if out is not None:
            return out
        fd = self.proc.stdout.fileno()
        ready, _, _ = select.select([fd], [], [], max(0.0, timeout))
        if not ready:
            return None
        chunk = os.read(fd, 1 << 20)
        if not chunk:  # ended without an error frame: stopped by a signal (LinuxCNC's shutdown), or it broke
            code = self.proc.wait(10)
            killed = code < 0 or code >= 128  # a signal (runuser reports signal n as 128 + n)
            cls = HalUnavailable if killed or code == 0 or code in WAIT_CODES else HalError
            raise cls(f"the HAL helper ended (exit code {code}){self._tail()}")
        self._buf += chunk
        return self._next()

    def _next(self) -> Hello | Frame | None:
        if len(self._buf) < _HEAD.size:
            return None
        size, kind = _HEAD.unpack_from(self._buf)
        if size > MAX_FRAME:
            raise HalError(f"the HAL helper sent a frame of {size} bytes (at most {MAX_FRAME})")
        end = _HEAD.size + size
        if len(self._buf) < end:
            return None
        payload = bytes(self._buf[_HEAD.size:end])
        del self._buf[:end]
        if kind == ord("D"):
            t_read, overruns, n, m = DATA_HEAD.unpack_from(payload)
            rows = np.frombuffer(payload, dtype="<f8", offset=DATA_HEAD.size, count=n * m).reshape(n, m)
            return Frame(t_read, overruns, rows)
        doc = json.loads(payload)
        if kind == ord("H"):
            return Hello(str(doc["types"]), int(doc["maxdepth"]), int(doc["overruns"]), int(doc["stale"]),
                         int(doc["session"]), int(doc["pid"]))
        code = self.proc.wait(10)
        cls = HalUnavailable if code in WAIT_CODES else HalError
        raise cls(str(doc.get("error", doc)))

    def set_pins(self, values: dict[str, float | int | bool]) -> bool:
        """Set way-back pins (thread safe); False when the helper is gone."""
        line = (json.dumps(values) + "\n").encode()
        with self._lock:
            try:
                self.proc.stdin.write(line)
                self.proc.stdin.flush()
                return True
            except (BrokenPipeError, ValueError, OSError):
                return False

    def close(self, timeout: float = 10.0) -> int | None:
        """End the helper (EOF on its stdin; SIGTERM, then SIGKILL if it lingers); its exit code."""
        with self._lock:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
        for sig in (None, signal.SIGTERM, signal.SIGKILL):
            if sig is not None:
                try:
                    os.killpg(self.proc.pid, sig)  # its own session: runuser and the helper
                except ProcessLookupError:
                    pass
            try:
                return self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                continue
        return None
