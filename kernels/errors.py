""":class:`ParameterError`: a bad argument of a library call, naming the Python parameter(s).

Library code (``kernels``, ``feedio``, ``monitor``, ``replay``) words its errors in its own
parameters (``period``, ``coulomb=False``, ``mapping``) and says the fix; it never names a
command-line flag. ``parameters`` lists the parameter names, so a front end can add its own
spelling: ``feedmon``'s CLI appends ``(command line: --period)`` from one table
(:mod:`feedmon.errors`). A subclass of ``ValueError``: ``except ValueError`` keeps working.

The CLI reads ``parameters`` from any exception it reports, so an ``OSError`` about an argument
may carry it too (:func:`feedio.transport.open_session`).

This module imports nothing: ``feedio``, ``monitor`` and ``replay`` all sit above ``kernels``.
"""

from __future__ import annotations

__all__ = ["ParameterError"]


class ParameterError(ValueError):
    """``ParameterError(message, *parameters)``: ``message`` names the parameter(s) and the fix;
    ``parameters`` (a tuple of names, e.g. ``("period",)``) says which, for a front end's hint."""

    def __init__(self, message: str, *parameters: str) -> None:
        super().__init__(message)
        self.parameters: tuple[str, ...] = tuple(parameters)
