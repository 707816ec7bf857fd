"""Output sinks of the monitor: each one a :class:`QueuedSink` on its own thread.

* :class:`~monitor.sinks.queued.QueuedSink` - bounded queue + worker thread base.
* :class:`~monitor.sinks.mcap_sink.McapSink` - MCAP log of samples and estimates.
* :class:`~monitor.sinks.rerun_sink.RerunSink` - Rerun recording (.rrd file and/or live gRPC server).
* :class:`~monitor.sinks.rerun_process.RerunProcessSink` - the same in a child process (what
  ``feedmon run`` uses: Rerun's batching never holds the monitor's GIL).

The MCAP and Rerun sinks are imported lazily (``from monitor.sinks.mcap_sink import McapSink``)
so that importing this package does not pull in rerun.
"""

from .queued import QueuedSink, SinkStatus

__all__ = ["QueuedSink", "SinkStatus"]
