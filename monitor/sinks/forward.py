"""``RerunForwardSink``: the Rerun recording process fed with the bytes the monitor already has.

:class:`~monitor.sinks.rerun_process.RerunProcessSink` takes schema objects and encodes each one
again on its worker thread before writing it to the recording process' pipe. The live monitor has
those bytes already — the sample block as received from Zenoh, the estimate as published — so this
subclass takes them (``offer_encoded``, the interface of
:class:`~monitor.sinks.mcap_sink.McapProcessSink`) and writes them to the pipe as they are, in the
recording process' wire format (:class:`~monitor.sinks.frames.Tag` ``SAMPLES`` + SampleBlock JSON, ``ESTIMATES``
+ EstimateBlock JSON, ``TRUTH`` + ``machine\\0axis\\0`` + TruthBlock JSON; see :mod:`monitor.sinks.rerun_process`). The monitor then
makes no :class:`~feedio.schema.EstimateBlock` object at all and its sink thread holds the
interpreter lock only to join bytes. The recording process decodes them with the schema as before
(a block as received from a bridge is valid JSON of the schema: the monitor decoded it). Objects
offered with ``offer`` still work (events, health, tests).
"""

from __future__ import annotations

from typing import Any

from .frames import Tag
from .rerun_process import RerunProcessSink

__all__ = ["RerunForwardSink"]


class _Encoded:
    """A message for the recording process, already in its wire format."""

    __slots__ = ("wire",)

    def __init__(self, wire: bytes) -> None:
        self.wire = wire


class RerunForwardSink(RerunProcessSink):
    """:class:`RerunProcessSink` that also takes encoded messages (module docstring); same arguments."""

    def offer_encoded(self, tag: Tag, payload: bytes, received_ns: int, head: bytes = b"") -> bool:
        """Queue one encoded message: ``tag`` ``SAMPLES`` (SampleBlock JSON), ``ESTIMATES`` (EstimateBlock
        JSON) or ``TRUTH`` (TruthBlock JSON, ``head`` = ``b"machine\\0axis"``). ``received_ns`` is not used (the
        recording is stamped with controller time)."""
        if tag == Tag.TRUTH:
            wire = Tag.TRUTH + head + b"\0" + payload
        elif tag == Tag.SAMPLES or tag == Tag.ESTIMATES:
            wire = tag + payload
        else:
            raise ValueError(f"RerunForwardSink: unknown tag {tag!r}")
        return self.offer(_Encoded(wire), len(wire))

    def handle(self, item: Any) -> None:
        if isinstance(item, _Encoded):
            self._send(item.wire, 1)
        else:
            super().handle(item)
