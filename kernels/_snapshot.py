"""Copying a snapshot's named arrays into a state's views (one definition for the KRLS-T, β and
health states): every field present, of the view's shape and of a kind it can hold."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

# what each destination kind accepts: integers only where indices live, real numbers for floats
_ACCEPTS = {"i": "iu", "u": "u", "f": "fiu", "b": "b"}


def fill_views(views, snap: Mapping, fields: Iterable[str], *, prefix: str = "", what: str = "snapshot") -> None:
    """``views.<name>[...] = snap[prefix + name]`` for each of ``fields``, after checking them all;
    raises ``ValueError`` naming the entry (missing, another shape, another kind) and changes nothing
    then. ``views`` is a NamedTuple of arrays (the state views of a compiled core)."""
    checked = []
    for name in fields:
        key = prefix + name
        if key not in snap:
            raise ValueError(f"{what} is missing {key!r}")
        arr = np.asarray(snap[key])
        dst = getattr(views, name)
        if arr.shape != dst.shape:
            raise ValueError(f"{what} {key!r} has shape {arr.shape}, expected {dst.shape} (another model or budget)")
        if arr.dtype.kind not in _ACCEPTS.get(dst.dtype.kind, dst.dtype.kind):
            raise ValueError(f"{what} {key!r} holds {arr.dtype}, expected {dst.dtype}")
        checked.append((dst, arr))
    for dst, arr in checked:
        dst[...] = arr
