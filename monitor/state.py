"""Tracker state on disk: :class:`StateStore` saves each axis' :meth:`AxisEstimator.snapshot`
with ``np.savez`` (plain arrays; loaded with ``allow_pickle=False``) plus the model file's
SHA-256. A state whose hash differs from the model file now in use is ignored with a warning
(the model changed: its tracker state is meaningless)."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np

from .axes import AxisRuntime
from .estimator import AxisEstimator

__all__ = ["StateStore", "STATE_FORMAT"]

log = logging.getLogger("monitor.state")

STATE_FORMAT = 1


class StateStore:
    """Where tracker snapshots live: ``<dir>/<machine>_<axis>.state.npz`` with ``state_dir``,
    else next to the model file (``axis-x.model.toml`` → ``axis-x.model.state.npz``)."""

    def __init__(self, state_dir: str | os.PathLike | None = None) -> None:
        self.dir = None if state_dir is None else Path(state_dir)
        if self.dir is not None and not self.dir.is_dir():
            self.dir.mkdir(parents=True, exist_ok=True)  # OSError: reported by the CLI

    def path_for(self, ax: AxisRuntime) -> Path:
        if self.dir is not None:
            return self.dir / f"{ax.model.machine}_{ax.model.axis}.state.npz"
        mp = Path(ax.status.model_path)
        stem = mp.name[:-5] if mp.name.endswith(".toml") else mp.name
        return mp.with_name(stem + ".state.npz")

    def save(self, ax: AxisRuntime) -> Path:
        """Atomically write the axis' snapshot (+ model hash)."""
        path = self.path_for(ax)
        snap = dict(ax.estimator.snapshot())
        snap["meta.format"] = np.array(STATE_FORMAT, dtype=np.int64)
        snap["meta.model_sha256"] = np.array(ax.status.model_sha256)
        snap["meta.machine"] = np.array(ax.model.machine)
        snap["meta.axis"] = np.array(ax.model.axis)
        snap["meta.saved_unix"] = np.array(time.time())
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, **snap)
        os.replace(tmp, path)
        ax.status.state_path = str(path)
        return path

    def load(self, ax: AxisRuntime) -> str:
        """Restore the axis' tracker if a matching state exists; returns what happened:
        ``fresh`` (none), ``restored``, ``ignored`` (other model) or ``unreadable``."""
        path = self.path_for(ax)
        ax.status.state_path = str(path)
        if not path.exists():
            ax.status.state = "fresh"
            return "fresh"
        try:
            with np.load(path, allow_pickle=False) as z:
                snap = {k: z[k] for k in z.files}
        except Exception as exc:  # noqa: BLE001 - corrupt file: warn and start fresh
            log.warning("tracker state %s of %s is unreadable (%s); starting fresh", path, ax.status.name, exc)
            ax.status.state = "unreadable"
            return "unreadable"
        saved = str(snap.pop("meta.model_sha256", np.array(""))[()])
        if saved != ax.status.model_sha256:
            log.warning("tracker state %s was saved with another model file (sha256 %s…, now %s…); "
                        "ignoring it and starting fresh", path, saved[:12], ax.status.model_sha256[:12])
            ax.status.state = "ignored"
            return "ignored"
        try:
            ax.estimator.restore({k: v for k, v in snap.items() if not k.startswith("meta.")})
        except Exception as exc:  # noqa: BLE001
            log.warning("tracker state %s of %s cannot be restored (%s); starting fresh", path, ax.status.name, exc)
            ax.estimator = AxisEstimator(ax.model)
            ax.status.state = "unreadable"
            return "unreadable"
        ax.status.state = "restored"
        return "restored"

