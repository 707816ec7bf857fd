"""An in-process :class:`~monitor.daemon.Monitor` on a real Zenoh session (loopback, free port) with a
matched publishing session: one definition for the lifecycle and fast-path tests."""

from __future__ import annotations

import time

import zenoh
from test_bad_input import PREFIX

from feedio import transport as T
from monitor.daemon import Monitor

KEY = T.samples_key(PREFIX, "linear-drive", "Z")


class Live:
    """A Monitor on a listening session plus a publishing session on ``key``, matched."""

    def __init__(self, axes, *, prefix: str = PREFIX, key: str = KEY, **kw):
        self.endpoint = f"tcp/127.0.0.1:{T.free_tcp_port()}"
        self.ms = T.open_session(listen=self.endpoint)
        self.monitor = Monitor(axes, self.ms, prefix=prefix, **kw)
        self.monitor.start()
        self.s = T.open_session(connect=self.endpoint)
        self.pub = self.s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        assert T.wait_for_matching(self.pub, 10.0)

    def wait(self, pred, timeout: float = 60.0) -> None:
        """Until ``pred(monitor)`` holds (a condition, polled), at most ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while not pred(self.monitor):
            assert time.monotonic() < deadline, self.monitor.status()
            time.sleep(0.01)

    def close(self) -> list[str]:
        """Stop the monitor (its problems are returned) and close both sessions."""
        problems = self.monitor.stop()
        self.s.close()
        self.ms.close()
        return problems
