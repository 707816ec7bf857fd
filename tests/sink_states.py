"""What a sink's state may be while it works: ``degraded`` is a working sink whose child was late with its
heartbeat — on a loaded host (the suite's two workers, a busy machine) its idle-priority process is starved
for a while before it is moved up. A test whose point is that a sink works, not how fast, accepts both."""

WORKING = ("ok", "degraded")
