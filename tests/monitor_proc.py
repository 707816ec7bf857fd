"""``feedmon run`` as a real subprocess for the end-to-end and fault tests (one definition)."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
from pathlib import Path

from feedio import transport as T

READY_TIMEOUT = 60.0  # s: start-up includes loading the Numba cache (or compiling on a cold one)


class MonitorProc:
    """``feedmon run`` as a subprocess on a free port; stderr collected by a thread."""

    def __init__(self, args: list[str], cwd: Path, *, prefix: str, listen: bool = True, preexec_fn=None):
        self.port = T.free_tcp_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        cmd = [sys.executable, "-m", "feedmon.cli", "run", "--prefix", prefix, *args]
        if listen:
            cmd[4:4] = ["--listen", self.endpoint]
        self.proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     preexec_fn=preexec_fn)
        self.lines: list[str] = []
        self._ready = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        if not self._ready.wait(READY_TIMEOUT):
            self.proc.kill()
            raise AssertionError("monitor did not get ready:\n" + self.stderr)
        if self.proc.poll() is not None:
            self._reader.join(5)
            raise AssertionError(f"monitor exited with {self.proc.returncode}:\n" + self.stderr)

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line)
            if "ready" in line and "listening on" in line:
                self._ready.set()
        self._ready.set()  # EOF: the process ended

    @property
    def stderr(self) -> str:
        return "".join(self.lines)

    def count(self, text: str) -> int:
        return sum(text in line for line in list(self.lines))

    def stop(self, sig=None, timeout: float = 60.0) -> int:
        """Signal (SIGTERM by default) and wait; the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig or signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
            raise AssertionError(f"monitor did not stop within {timeout:.0f} s:\n{self.stderr}") from None
        self._reader.join(5)
        return rc
