"""Process monitoring on the estimated feed force: settings, the per-axis monitor, reference files, the wear
history across parts (:mod:`.wear`).

Data flow: sample → residual → tracker → estimate → **process monitor** → alarm events → sinks. The
numerics are in :mod:`kernels.force_monitors`; what each monitor does and how its limits are set is in
``docs/process-monitoring.md``.
"""

from .monitor import AxisProcessMonitor, ProcessMonitors, build_monitors
from .settings import MonitorSettings

__all__ = ["AxisProcessMonitor", "ProcessMonitors", "MonitorSettings", "build_monitors"]
