"""How the command line reports an error: the library's message, then the flags of the parameters it
names (style.md, "library vs CLI").

Library code raises :class:`kernels.errors.ParameterError` (a ``ValueError``) whose text names the
Python parameter (``period``, ``coulomb=False``, ``mapping``) and whose ``parameters`` lists them;
:data:`FLAGS` says which option of each sub-command sets that parameter, and :func:`describe` appends
``(command line: --period)``. Every sub-command's errors go through :func:`report`
(:func:`feedmon.cli.main`).
"""

from __future__ import annotations

import sys

__all__ = ["FLAGS", "flags_for", "describe", "report"]

_ZENOH = {"connect": "--connect", "listen": "--listen"}

#: sub-command -> library parameter -> the option that sets it
FLAGS: dict[str, dict[str, str]] = {
    "identify": {
        "period": "--period", "spindle_rpm": "--spindle-rpm", "method": "--method", "form": "--form",
        "sigma1": "--sigma1", "sigma2": "--sigma2", "gamma": "--gamma", "omega": "--omega",
        "coulomb": "--coulomb/--no-coulomb", "loop_gain": "--loop-gain", "start": "--start", "end": "--end",
    },
    "import": {"rate": "--rate", "mapping": "--map", "units": "--units", "form": "--form", "Ts": "--Ts",
               "loop_gain": "--loop-gain"},
    "simulate": {"fine": "--fine"},
    "replay": {"rate": "--rate/--max", "block": "--block", "loop": "--loop/--passes", **_ZENOH},
    "demo": {"rate": "--rate"},
    "run": {"model_paths": "--model", "axes": "--model", "config": "--config", **_ZENOH},
    "status": dict(_ZENOH),
    "bridge": {"scale": "--scale", "servo_period": "--servo-period", **_ZENOH},
}


def flags_for(exc: BaseException, command: str | None) -> list[str]:
    """The options of ``command`` that set the parameters ``exc`` names (its ``parameters``), in order."""
    table = FLAGS.get(command or "", {})
    out: list[str] = []
    for name in getattr(exc, "parameters", ()) or ():
        flag = table.get(name)
        if flag is not None and flag not in out:
            out.append(flag)
    return out


def describe(exc: BaseException, command: str | None) -> str:
    """``exc``'s message, with ``(command line: --flag, …)`` when it names parameters of ``command``."""
    flags = flags_for(exc, command)
    return f"{exc} (command line: {', '.join(flags)})" if flags else str(exc)


def report(exc: BaseException, command: str | None) -> None:
    """Print ``feedmon COMMAND: error: …`` (:func:`describe`) on stderr."""
    print(f"feedmon {command}: error: {describe(exc, command)}", file=sys.stderr)
