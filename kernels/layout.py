"""One declarative field list per compiled state: the named views of two base buffers.

A compiled state (the KRLS-T core's :class:`~kernels._krlst_core.State`, the online β's
:class:`~kernels.beta_tracker.BetaState`, health's :class:`~kernels.health.HealthState`, the online
loop's :class:`~kernels.online.OnlineState`) is a ``NamedTuple`` of arrays that are views of one
``float64`` and one ``int64`` buffer. A :class:`Layout` is built from a list of :class:`Field` (name,
dtype, shape expression, role) and generates everything else from it: the ``NamedTuple``, the offsets,
the NumPy views (:meth:`Layout.views`) and the accessor for compiled code (:meth:`Layout.accessor`),
whose source is generated once at import and compiled by numba like hand-written code (the offsets are
straight-line integer arithmetic on the header, the views cost nothing). The roles give the snapshot
fields (:meth:`Layout.names`).

Shapes are tuples of integers or expressions over the layout's *dims* (integers stored at the start
of the ``int64`` buffer, read back by the accessors) and the constants passed in ``consts``.
"""

from __future__ import annotations

import ast
import collections
import functools
import math
import threading
from typing import NamedTuple

import numpy as np
from numba import njit
from numba.extending import register_jitable

from ._krlst_simd import unowned_array, view

#: roles of a field: the dims header, settings fixed for a model, state (snapshots), scratch, outputs
ROLES = ("layout", "setting", "state", "scratch", "output")
_KINDS = {"f8": "f", "i8": "i"}


#: CPython 3.11's parser keeps one recursion count per interpreter, not per thread: two threads parsing at
#: once can raise "SystemError: AST constructor recursion depth mismatch" (python/cpython#106905). The
#: disturbance search builds trackers on a worker thread while the estimator builds its own.
_PARSE_LOCK = threading.Lock()


@functools.cache
def _parsed(expr: str) -> ast.expr:
    """A shape expression's syntax tree, parsed once (the trees are only read)."""
    with _PARSE_LOCK:
        return ast.parse(expr, mode="eval").body


def _dimension(expr: str, env: dict) -> int:
    """The value of a shape expression of a field list (names of dimensions and constants, integers, ``+``,
    ``-``, ``*``): parsed, never evaluated, so nothing but that arithmetic can run."""
    def value(node) -> int:
        if isinstance(node, ast.Constant) and isinstance(node.value, int):
            return node.value
        if isinstance(node, ast.Name) and node.id in env:
            return int(env[node.id])
        if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Sub, ast.Mult)):
            a, b = value(node.left), value(node.right)
            return a + b if isinstance(node.op, ast.Add) else a - b if isinstance(node.op, ast.Sub) else a * b
        raise ValueError(f"shape expression {expr!r}: only names of dimensions, integers, +, - and * are allowed")
    return value(_parsed(expr))

class Field(NamedTuple):
    """One field: ``dtype`` ``"f8"`` (the float buffer) or ``"i8"`` (the integer buffer); ``shape`` a
    tuple of ints or expressions (str) over the dims and constants; ``role`` one of :data:`ROLES`."""

    name: str
    dtype: str
    shape: tuple
    role: str
    doc: str = ""


class Layout:
    """The fields of one compiled state in two base buffers ``(float64, int64)``.

    ``dims`` name the integers at ``ibuf[0:len(dims)]`` the shapes depend on; ``align`` pads every
    float field to a multiple of that many doubles (64-byte rows for the 8-lane sweeps);
    ``placement`` the order of the fields in the buffers when it differs from the tuple's order.
    """

    def __init__(self, typename: str, module: str, fields, *, dims=(), consts=None, align: int = 1,
                 placement=None, doc: str = ""):
        self.typename = typename
        self.fields = tuple(fields)
        self.dims = tuple(dims)
        self.consts = dict(consts or {})
        self.align = int(align)
        names = [f.name for f in self.fields]
        if len(set(names)) != len(names):
            raise ValueError(f"{typename}: duplicate field names")
        for f in self.fields:
            if f.dtype not in _KINDS or f.role not in ROLES:
                raise ValueError(f"{typename}.{f.name}: dtype {f.dtype!r} or role {f.role!r} unknown")
        self.placement = tuple(placement) if placement is not None else tuple(names)
        if sorted(self.placement) != sorted(names):
            raise ValueError(f"{typename}: the placement must list every field once")
        self.tuple = collections.namedtuple(typename, names, module=module)
        self.tuple.__doc__ = doc or self.tuple.__doc__
        self._plans: dict[tuple, tuple[dict, int, int, tuple]] = {}

    # ---- Python side -------------------------------------------------------------------------------
    def names(self, *roles: str) -> tuple[str, ...]:
        """The field names of the given roles, in field order."""
        return tuple(f.name for f in self.fields if f.role in roles)

    def shape(self, field: Field, dims: dict) -> tuple[int, ...]:
        env = {**self.consts, **dims}
        return tuple(int(s) if isinstance(s, (int, np.integer)) else _dimension(s, env) for s in field.shape)

    def _pad(self, n: int, kind: str) -> int:
        a = self.align if kind == "f" else 1
        return (n + a - 1) // a * a

    def offsets(self, **dims) -> tuple[dict, int, int]:
        """``({name: offset}, float length, int length)`` for the given dims (the dict is shared: read it only)."""
        return self._plan(dims)[:3]

    def _plan(self, dims: dict) -> tuple[dict, int, int, tuple]:
        """Offsets, buffer lengths and the fields' shapes for ``dims``, worked out once per distinct dims:
        the disturbance search builds a tracker per candidate, and the shape expressions took a third of
        that."""
        key = tuple(sorted(dims.items()))
        plan = self._plans.get(key)
        if plan is None:
            by_name = {f.name: f for f in self.fields}
            shapes = {f.name: self.shape(f, dims) for f in self.fields}
            at = {"f": 0, "i": 0}
            out = {}
            for name in self.placement:
                kind = _KINDS[by_name[name].dtype]
                out[name] = at[kind]
                at[kind] += self._pad(math.prod(shapes[name]), kind)
            plan = (out, at["f"], at["i"], tuple(shapes[f.name] for f in self.fields))
            if len(self._plans) >= 64:            # a few budgets and input widths per process; bounded all the same
                self._plans.clear()
            self._plans[key] = plan
        return plan

    def new_buffers(self, aligned_zeros=np.zeros, **dims) -> tuple[np.ndarray, np.ndarray]:
        """Zeroed base buffers ``(float64, int64)`` for the dims, the dims written into the header."""
        _, nf, ni = self.offsets(**dims)
        fbuf = aligned_zeros(nf)
        ibuf = np.zeros(ni, dtype=np.int64)
        ibuf[:len(self.dims)] = [dims[d] for d in self.dims]
        return fbuf, ibuf

    def views(self, fbuf: np.ndarray, ibuf: np.ndarray):
        """The named NumPy views of the two base buffers (dims read from ``ibuf``'s header)."""
        dims = {d: int(ibuf[k]) for k, d in enumerate(self.dims)}
        at, _, _, shapes = self._plan(dims)
        out = []
        for f, shape in zip(self.fields, shapes):
            buf = fbuf if _KINDS[f.dtype] == "f" else ibuf
            out.append(buf[at[f.name]:at[f.name] + math.prod(shape)].reshape(shape))
        return self.tuple(*out)

    # ---- compiled side -----------------------------------------------------------------------------
    def _expr(self, s) -> str:
        return str(int(s)) if isinstance(s, (int, np.integer)) else f"({s})"

    def accessor_source(self, fname: str) -> str:
        """Source of ``fname(fbuf, ibuf)``: the state's reference-free views inside compiled code."""
        lines = [f"def {fname}(fbuf, ibuf):"]
        lines += [f"    {d} = ibuf[{k}]" for k, d in enumerate(self.dims)]
        by_name = {f.name: f for f in self.fields}
        at = {"f": "0", "i": "0"}
        for name in self.placement:
            f = by_name[name]
            kind = _KINDS[f.dtype]
            lines.append(f"    o_{name} = {at[kind]}")
            size = " * ".join(self._expr(s) for s in f.shape) or "1"
            a = self.align if kind == "f" else 1
            padded = f"(({size}) + {a - 1}) // {a} * {a}" if a > 1 else f"({size})"
            at[kind] = f"o_{name} + {padded}"
        args = []
        for f in self.fields:
            buf = "fbuf" if _KINDS[f.dtype] == "f" else "ibuf"
            shape = ", ".join(self._expr(s) for s in f.shape) + ("," if len(f.shape) == 1 else "")
            args.append(f"_view({buf}, o_{f.name}, ({shape}))")
        lines.append(f"    return _T({', '.join(args)})")
        return "\n".join(lines) + "\n"

    def unowned_source(self, fname: str) -> str:
        """Source of ``fname(st)``: ``st`` with reference-free arrays (no reference counting when passed on)."""
        args = ", ".join(f"_u(st.{f.name})" for f in self.fields)
        return f"def {fname}(st):\n    return _T({args})\n"

    def _compile(self, src: str, fname: str, filename: str, **extra):
        ns = {"_T": self.tuple, "_view": view, "_u": unowned_array, **self.consts, **extra}
        # the file of the module that owns the layout: numba's cache is keyed on it (and on the
        # bytecode), so a changed field list invalidates the cached callers with it
        with _PARSE_LOCK:
            code = compile(src, filename, "exec")
        exec(code, ns)
        fn = ns[fname]
        fn.__module__ = self.tuple.__module__
        fn.__qualname__ = f"{self.typename}_{fname}"
        return fn

    def accessor(self, fname: str, filename: str):
        """The compiled accessor ``fname(fbuf, ibuf)`` (:meth:`accessor_source`), inlined into its callers."""
        fn = self._compile(self.accessor_source(fname), fname, filename)
        return njit(cache=True, nogil=True, inline="always")(fn)

    def sliced(self, fname: str, filename: str, *, ints_first: bool = False):
        """``fname(fbuf, ibuf)`` (``fname(ibuf, fbuf)`` with ``ints_first``): the named views as slices of
        the buffers, for a layout without dims; works in Python and inside compiled code (compiled into
        its caller)."""
        at, _, _ = self.offsets()
        parts = []
        for f in self.fields:
            if len(f.shape) != 1:
                raise ValueError(f"{self.typename}.{f.name}: sliced views are 1-D")
            n = self.shape(f, {})[0]
            parts.append(f"{'fbuf' if _KINDS[f.dtype] == 'f' else 'ibuf'}[{at[f.name]}:{at[f.name] + n}]")
        sig = "ibuf, fbuf" if ints_first else "fbuf, ibuf"
        src = f"def {fname}({sig}):\n    return _T({', '.join(parts)})\n"
        return register_jitable(self._compile(src, fname, filename))

    def unowned(self, fname: str, filename: str):
        """The compiled :meth:`unowned_source`, inlined into its callers."""
        fn = self._compile(self.unowned_source(fname), fname, filename)
        return njit(cache=True, nogil=True, inline="always")(fn)


class Record:
    """A ``NamedTuple`` of scalars stored in one ``int64`` and one ``float64`` array, read by compiled code
    (a loop's settings): ``fields`` of dtype ``"bool"``, ``"i8"`` (both in the integer array) or ``"f8"``,
    shape ``()``; ``head`` names arrays passed through unchanged before them."""

    def __init__(self, typename: str, module: str, fields, *, head=(), doc: str = ""):
        self.typename = typename
        self.fields = tuple(fields)
        self.head = tuple(head)
        for f in self.fields:
            if f.dtype not in ("bool", "i8", "f8") or f.shape != ():
                raise ValueError(f"{typename}.{f.name}: a record holds scalars of dtype bool, i8 or f8")
        self.int_names = tuple(f.name for f in self.fields if f.dtype != "f8")
        self.float_names = tuple(f.name for f in self.fields if f.dtype == "f8")
        #: ``{name: index}`` into the integer and the float array
        self.int_slot = {n: i for i, n in enumerate(self.int_names)}
        self.float_slot = {n: i for i, n in enumerate(self.float_names)}
        self.tuple = collections.namedtuple(typename, self.head + tuple(f.name for f in self.fields), module=module)
        self.tuple.__doc__ = doc or self.tuple.__doc__

    def pack(self, **values) -> tuple[np.ndarray, np.ndarray]:
        """``(ints, floats)`` holding ``values`` (every field by name)."""
        missing = set(self.int_names + self.float_names) - set(values)
        if missing:
            raise ValueError(f"{self.typename}: no value for {sorted(missing)}")
        return (np.array([int(values[n]) for n in self.int_names], dtype=np.int64),
                np.array([float(values[n]) for n in self.float_names], dtype=np.float64))

    def accessor_source(self, fname: str) -> str:
        args = []
        for f in self.fields:
            if f.dtype == "f8":
                args.append(f"floats[{self.float_slot[f.name]}]")
            else:
                args.append(f"ints[{self.int_slot[f.name]}]" + (" != 0" if f.dtype == "bool" else ""))
        sig = ", ".join(self.head + ("ints", "floats"))
        return f"def {fname}({sig}):\n    return _T({', '.join(self.head + tuple(args))})\n"

    def accessor(self, fname: str, filename: str):
        """``fname(*head, ints, floats)``: the named values; works in Python and inside compiled code."""
        ns = {"_T": self.tuple}
        with _PARSE_LOCK:
            code = compile(self.accessor_source(fname), filename, "exec")
        exec(code, ns)
        fn = ns[fname]
        fn.__module__ = self.tuple.__module__
        return register_jitable(fn)


__all__ = ["Field", "Layout", "Record", "ROLES"]
