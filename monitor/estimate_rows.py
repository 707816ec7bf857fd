"""The estimate rows of one block as the compiled loop wrote them (:class:`EstimateRows`), and the
:class:`~feedio.schema.EstimateBlock` and its JSON made from them — only when someone asks: the live
monitor publishes the JSON, the offline runner writes it, the sinks take the schema object."""

from __future__ import annotations

import msgspec
import numpy as np

from feedio.schema import EstimateBlock
from kernels import online

__all__ = ["EstimateRows"]


_json = msgspec.json.Encoder()
#: JSON keys of the columns of an EstimateBlock after machine, axis and seq, in field order
_COLUMN_KEYS = [f',"{name}":'.encode() for name in EstimateBlock.__struct_fields__[3:]]


class EstimateRows:
    """The estimate rows of one block as the compiled loop wrote them (columns, no per-sample
    Python objects): ``seq`` of the first row, ``t`` (s), ``v_meas`` (m/s), ``rows``
    (:data:`kernels.online.ROWS`, float64), ``irows`` (:data:`kernels.online.IROWS`, int64) and
    ``force`` (``force``, ``force_var``, ``force_next`` in N, or None when the model cannot scale) and
    ``context`` (the context columns of the rows' samples, :data:`~feedio.schema.CONTEXT_COLUMNS`, as given).
    :meth:`block` makes the :class:`~feedio.schema.EstimateBlock` (once), :meth:`scalar_columns`
    the per-sample columns of :meth:`feedio.scalars.ScalarsPairer.add_rows`."""

    __slots__ = ("machine", "axis", "seq", "t", "v_meas", "rows", "irows", "force", "context", "_cols", "_block",
                 "_json")

    def __init__(self, machine: str, axis: str, seq: int, t: np.ndarray, v_meas: np.ndarray, rows: np.ndarray,
                 irows: np.ndarray, force: np.ndarray | None, context: dict[str, list] | None = None) -> None:
        self.machine, self.axis, self.seq = machine, axis, seq
        self.t, self.v_meas, self.rows, self.irows, self.force = t, v_meas, rows, irows, force
        self.context = context or {}
        self._cols: list[list] | None = None
        self._block: EstimateBlock | None = None
        self._json: bytes | None = None

    def __len__(self) -> int:
        return int(self.t.size)

    def _columns(self) -> list[list]:
        """The columns after machine, axis and seq as lists, in EstimateBlock field order (made once,
        shared by :meth:`block` and :meth:`json`)."""
        if self._cols is None:
            cols = [self.t.tolist(), self.v_meas.tolist(), *self.rows.tolist(), *self.irows.tolist()]
            if self.force is not None:
                cols += self.force.tolist()
            self._cols = cols
        return self._cols

    def block(self) -> EstimateBlock:
        """The :class:`~feedio.schema.EstimateBlock` (made on the first call; the columns of
        :data:`~kernels.online.ROWS` and :data:`~kernels.online.IROWS` are its fields in that order)."""
        if self._block is None:
            self._block = EstimateBlock(self.machine, self.axis, self.seq, *self._columns(), **self.context)
        return self._block

    def json(self) -> bytes:
        """The JSON of :meth:`block` — the bytes ``feedio.schema.encode(self.block())`` gives — made
        from the columns with one ``msgspec`` call, without the schema object (the live monitor
        publishes it before anything else). Names match ``NAME_PATTERN`` (no character to escape)."""
        if self._json is None:
            parts = _json.encode(self._columns())[2:-2].split(b"],[")  # "[[c0],[c1],…]" -> c0, c1, …
            body = [f'{{"machine":"{self.machine}","axis":"{self.axis}","seq":{self.seq}'.encode()]
            for key, part in zip(_COLUMN_KEYS, parts):
                body += (key, b"[", part, b"]")
            for name, col in self.context.items():  # after the force columns, in field order
                body += (f',"{name}":'.encode(), _json.encode(col))
            body.append(b"}")
            self._json = b"".join(body)
        return self._json

    def scalar_columns(self) -> dict[str, np.ndarray | None]:
        """The columns :meth:`feedio.scalars.ScalarsPairer.add_rows` takes (views, no copies):
        ``v_meas, f, f_var, f_next``, ``force, force_var, force_next`` (None without a force scale) and
        ``flags``."""
        r, fc = self.rows, self.force
        return {"v_meas": self.v_meas, "f": r[online.R_F], "f_var": r[online.R_FVAR], "f_next": r[online.R_FNEXT],
                "force": None if fc is None else fc[0], "force_var": None if fc is None else fc[1],
                "force_next": None if fc is None else fc[2], "flags": self.irows[online.R_FLAGS]}
