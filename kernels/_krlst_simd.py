"""Low-level intrinsics of the KRLS-T core: explicit 8-lane sweeps over symmetric matrices kept as
a strict upper triangle plus a diagonal, a scalar ``fmuladd`` and reference-free array views.

The sweeps are :mod:`kernels._krlst_core`'s three ``O(M²)`` passes (``q = Q k_t``, ``h = Σ q``,
``Q μ_new``), each fused with the rank-one updates that are pending on the matrix.

Storage
-------
A symmetric ``n×n`` matrix ``S`` lives in a C-contiguous ``(n8, n8)`` array ``U`` (``n8`` a
multiple of 8) holding its *strict* upper triangle (``U[j, i] = S[j, i]`` for ``i > j``,
everything else 0) and a vector ``d`` holding its diagonal. A sweep over row ``j`` reads the
columns ``[j & ~7, hi8)`` in blocks of 8: the few entries left of the diagonal in the first
block are the zeros of the lower triangle, so every block is a full vector and
``S z = U z + Uᵀ z + d∘z`` needs no remainder loops. Half the matrix is read and written.

Why explicit vectors
--------------------
With half the matrix, ``U z`` is a row *dot product* (``Uᵀ z`` stays a row-wise axpy). numba's
LLVM pipeline vectorises a floating-point sum only with reassociation (results then depend on
the vector width and on how a function is inlined) and does not run the SLP vectoriser. Here the
lanes are part of the arithmetic: lane ``l`` of a dot accumulates the columns ``i ≡ l (mod 8)``
and the lanes are added in the fixed order ``((0+1)+(2+3))+((4+5)+(6+7))``. Multiply–adds are
``llvm.fmuladd``: fused where the CPU has FMA, separate elsewhere, so one process always gets
the same bits from every caller, and two CPUs agree to rounding.

Blocking
--------
A call handles :data:`SWEEP_ROWS` = 8 consecutive rows ``j … j+7`` (``j % 8 == 0``, so they share the
first column block, the only one that needs a mask). Per column block each row's entries are
loaded, updated and stored once, the axpy target ``t`` is loaded and stored once for the eight
rows, and each row keeps its own dot accumulator (independent dependency chains); the eight
diagonal entries and the eight finished entries of ``t`` are then handled as one vector.
On the 2-core Xeon of the benchmarks the sweeps run at about the FMA throughput: at ``M = 100``
one multiply–add per stored entry costs ~0.2 µs per pass, with 4- or 8-lane vectors alike.
"""

from __future__ import annotations

import inspect

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

LANES = 8
SWEEP_ROWS = 8

_DBL = ir.DoubleType()
_I32 = ir.IntType(32)
_I64 = ir.IntType(64)
_VEC = ir.VectorType(_DBL, LANES)
_VECR = ir.VectorType(_DBL, SWEEP_ROWS)
_IVEC = ir.VectorType(_I64, LANES)


def _fma(builder, a, b, c):
    """``a·b + c`` lane by lane (``llvm.fmuladd``)."""
    vty = a.type
    fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vty, [vty, vty, vty]),
                                        f"llvm.fmuladd.v{vty.count}f64")
    return builder.call(fn, [a, b, c])


def _splat(builder, x, vty=_VEC):
    v = builder.insert_element(ir.Constant(vty, ir.Undefined), x, ir.Constant(_I32, 0))
    return builder.shuffle_vector(v, ir.Constant(vty, ir.Undefined), ir.Constant(ir.VectorType(_I32, vty.count),
                                                                                [0] * vty.count))


def _lane_sums(builder, a, b, c, d):
    """``[Σa, Σb, Σc, Σd]`` (a ``<4 x double>``), each 8-lane accumulator summed in the fixed order
    ``((v0+v1)+(v2+v3)) + ((v4+v5)+(v6+v7))`` of a dot's lanes, by shuffles (a transposed reduction:
    the same additions)."""
    def shuf(x, y, idx):
        return builder.shuffle_vector(x, y, ir.Constant(ir.VectorType(_I32, len(idx)), idx))

    # [a0+a1, b0+b1, a2+a3, b2+b3, a4+a5, b4+b5, a6+a7, b6+b7], the same for c, d
    ab = builder.fadd(shuf(a, b, [0, 8, 2, 10, 4, 12, 6, 14]), shuf(a, b, [1, 9, 3, 11, 5, 13, 7, 15]))
    cd = builder.fadd(shuf(c, d, [0, 8, 2, 10, 4, 12, 6, 14]), shuf(c, d, [1, 9, 3, 11, 5, 13, 7, 15]))
    # [a(01+23), b(01+23), c(01+23), d(01+23), a(45+67), b(45+67), c(45+67), d(45+67)]
    abcd = builder.fadd(shuf(ab, cd, [0, 1, 8, 9, 4, 5, 12, 13]), shuf(ab, cd, [2, 3, 10, 11, 6, 7, 14, 15]))
    und = ir.Constant(_VEC, ir.Undefined)
    return builder.fadd(shuf(abcd, und, [0, 1, 2, 3]), shuf(abcd, und, [4, 5, 6, 7]))


def _row_sums(builder, accs):
    """The ``SWEEP_ROWS`` lane sums (:func:`_lane_sums`) as one ``<SWEEP_ROWS x double>``."""
    quads = [_lane_sums(builder, *accs[k:k + 4]) for k in range(0, len(accs), 4)]
    if len(quads) == 1:
        return quads[0]
    return builder.shuffle_vector(quads[0], quads[1], ir.Constant(ir.VectorType(_I32, 8), list(range(8))))


class Stream:
    """What a sweep does with one symmetric matrix (arguments, in this order, after ``j, hi8``):

    * ``U``, ``d`` — its strict upper triangle ``(n8, n8)`` and diagonal ``(n8,)``, float64;
    * ``terms`` pairs ``(c, x)``: rank-one terms, ``S ← S + c x xᵀ`` (row ``r``: ``v += (c·x_r) x``);
    * ``scale``: one float ``λ``, then ``S ← λ S``;
    * ``store``: the updated rows are written back (``U`` only right of the diagonal: its lower
      triangle and diagonal stay 0), and the diagonal to ``d``;
    * ``vecs`` pairs ``(t, z)``: ``t += S z`` for these rows' part of ``S`` — ``t[i] += z_r v_i``
      (the ``Uᵀ z`` half, in row order) for every column, and ``t[r] += (Σ_i v_i z_i) + d_r z_r``
      (the ``U z`` half and the diagonal) for the rows themselves, once all earlier rows are in.
    """

    def __init__(self, terms: int = 0, scale: bool = False, store: bool = False, vecs: int = 1):
        self.terms, self.scale, self.store, self.vecs = terms, scale, store, vecs

    @property
    def kinds(self) -> list[str]:
        """Argument kinds: ``a`` array, ``f`` float."""
        return ["a", "a"] + ["f", "a"] * self.terms + ["f"] * int(self.scale) + ["a", "a"] * self.vecs


def sweep(*streams: Stream):
    """An ``@intrinsic`` ``f(j, hi8, <stream args>…)`` sweeping rows ``j … j+3`` (``j % 4 == 0``) over
    the columns ``[j & ~7, hi8)`` (see :class:`Stream`); a sweep over all rows is a loop over ``j``."""
    kinds = ["i", "i"] + [k for s in streams for k in s.kinds]

    def typer(typingctx, *argtys):
        scalar = {"i": types.intp, "f": types.float64}
        sig = types.void(*[scalar.get(k, ty) for k, ty in zip(kinds, argtys)])

        def codegen(context, builder, sig, args):
            it = iter(zip(sig.args, args))

            def array():
                ty, val = next(it)
                return context.make_array(ty)(context, builder, val)

            def scalar():
                return next(it)[1]

            def ptr(data, idx, vty=_VEC):
                return builder.bitcast(builder.gep(data, [idx]), vty.as_pointer())

            def load(data, idx, vty=_VEC):
                return builder.load(ptr(data, idx, vty), align=8)

            j = scalar()
            hi = scalar()
            lo = builder.and_(j, ir.Constant(_I64, ~(LANES - 1)))
            zero = ir.Constant(_VEC, [0.0] * LANES)
            lane_index = ir.Constant(_IVEC, list(range(LANES)))
            rows = [builder.add(j, ir.Constant(_I64, r)) for r in range(SWEEP_ROWS)]
            row_splat = [_splat(builder, r, _IVEC) for r in rows]
            plan = []
            for s in streams:
                U = array()
                d = array()
                ncol = builder.extract_value(U.shape, 1)
                bases = [builder.mul(r, ncol) for r in rows]
                terms = []
                for _ in range(s.terms):
                    c = scalar()
                    x = array()
                    coefs = [builder.fmul(c, builder.load(builder.gep(x.data, [r]))) for r in rows]
                    terms.append((c, [_splat(builder, cr) for cr in coefs], x))
                lam = scalar() if s.scale else None
                vecs = []
                for _ in range(s.vecs):
                    t = array()
                    z = array()
                    z_row = [_splat(builder, builder.load(builder.gep(z.data, [r]))) for r in rows]
                    accs = [cgutils.alloca_once_value(builder, zero) for _ in rows]
                    vecs.append((t, z, z_row, accs))
                plan.append((s, U, d, bases, terms, lam, vecs))

            # ---- the rows' entries right of the diagonal, 8 columns at a time -------------------
            def block(c, first):
                """Columns ``c … c+7``; only the first block reaches left of (or onto) the diagonal."""
                col = builder.add(_splat(builder, c, _IVEC), lane_index)
                for s, U, _d, bases, terms, lam, vecs in plan:
                    xs = [load(x.data, c) for _, _, x in terms]
                    vals = []
                    for r in range(SWEEP_ROWS):
                        p = ptr(U.data, builder.add(bases[r], c))
                        v = builder.load(p, align=8)
                        for (_, coefs, _), xv in zip(terms, xs):
                            v = _fma(builder, coefs[r], xv, v)             # v += (c x_r) x
                        if lam is not None:
                            v = builder.fmul(_splat(builder, lam), v)       # v ← λ v
                        if terms or lam is not None:
                            if first:                                       # keep U's lower triangle 0
                                v = builder.select(builder.icmp_signed(">", col, row_splat[r]), v, zero)
                            if s.store:
                                builder.store(v, p, align=8)
                        vals.append(v)
                    for t, z, z_row, accs in vecs:
                        tp = ptr(t.data, c)
                        tv = builder.load(tp, align=8)
                        for r in range(SWEEP_ROWS):
                            tv = _fma(builder, z_row[r], vals[r], tv)     # t += z_r v   (Uᵀ z)
                        builder.store(tv, tp, align=8)
                        zv = load(z.data, c)
                        for r in range(SWEEP_ROWS):
                            builder.store(_fma(builder, vals[r], zv, builder.load(accs[r])), accs[r])  # U z

            block(lo, True)                               # (j < hi8: there is always a first block)
            nblocks = builder.udiv(builder.sub(hi, lo), ir.Constant(_I64, LANES))
            with cgutils.for_range(builder, builder.sub(nblocks, ir.Constant(_I64, 1))) as loop:
                block(builder.add(lo, builder.mul(builder.add(loop.index, ir.Constant(_I64, 1)),
                                                  ir.Constant(_I64, LANES))), False)

            # ---- the diagonal, then t[r] += (U z)_r + d_r z_r, the rows as one vector ---------------
            for s, _U, d, _bases, terms, lam, vecs in plan:
                dv = load(d.data, j, _VECR)
                for c, _, x in terms:
                    xv = load(x.data, j, _VECR)
                    dv = _fma(builder, builder.fmul(_splat(builder, c, _VECR), xv), xv, dv)
                if lam is not None:
                    dv = builder.fmul(_splat(builder, lam, _VECR), dv)
                if s.store and (terms or lam is not None):
                    builder.store(dv, ptr(d.data, j, _VECR), align=8)
                for t, z, _z_row, accs in vecs:
                    sums = _row_sums(builder, [builder.load(acc) for acc in accs])
                    tp = ptr(t.data, j, _VECR)
                    diag = builder.fmul(dv, load(z.data, j, _VECR))
                    builder.store(builder.fadd(builder.load(tp, align=8), builder.fadd(sums, diag)), tp, align=8)
            return context.get_dummy_value()

        return sig, codegen

    # @intrinsic reads the parameter list from the signature: give it a fixed one
    param = inspect.Parameter
    typer.__signature__ = inspect.Signature([param("typingctx", param.POSITIONAL_OR_KEYWORD)] + [
        param(f"a{i}", param.POSITIONAL_OR_KEYWORD) for i in range(len(kinds))])
    typer.__name__ = typer.__qualname__ = "sweep_" + "_".join(
        f"t{s.terms}{'s' if s.scale else ''}{'w' if s.store else ''}v{s.vecs}" for s in streams)
    return intrinsic(typer)


@intrinsic
def fmuladd(typingctx, a, b, c):
    """Scalar ``a·b + c`` with the same contraction rule as the sweeps (``llvm.fmuladd``)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, sig, args):
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_DBL, [_DBL, _DBL, _DBL]),
                                            "llvm.fmuladd.f64")
        return builder.call(fn, args)

    return sig, codegen


@intrinsic
def view(typingctx, base, offset, shape):
    """``base[offset:offset + prod(shape)].reshape(shape)`` (``base`` 1-D, C-contiguous) as an array that
    holds no reference to ``base``: no reference counting, so building a view costs nothing, and it
    is valid only while ``base`` is alive (never return it to Python)."""
    ndim = len(shape)
    retty = types.Array(base.dtype, ndim, "C")
    sig = retty(base, types.intp, shape)

    def codegen(context, builder, sig, args):
        src = context.make_array(sig.args[0])(context, builder, args[0])
        ary = context.make_array(retty)(context, builder)
        dims = [context.cast(builder, v, ty, types.intp)
                for v, ty in zip(cgutils.unpack_tuple(builder, args[2], ndim), sig.args[2])]
        itemsize = context.get_constant(types.intp, context.get_abi_sizeof(context.get_data_type(base.dtype)))
        strides = []
        step = itemsize
        for d in reversed(dims):
            strides.insert(0, step)
            step = builder.mul(step, d)
        context.populate_array(ary, data=builder.gep(src.data, [args[1]]), shape=dims, strides=strides,
                               itemsize=itemsize, meminfo=None)
        return ary._getvalue()

    return sig, codegen


@intrinsic
def unowned_array(typingctx, arr):
    """``arr`` without its reference to the memory's owner (see :func:`view`): passing it around
    compiled code costs no reference counting. Valid while the original array is alive."""
    sig = arr(arr)

    def codegen(context, builder, sig, args):
        src = context.make_array(sig.args[0])(context, builder, args[0])
        ary = context.make_array(sig.return_type)(context, builder)
        ndim = sig.args[0].ndim
        context.populate_array(ary, data=src.data, shape=cgutils.unpack_tuple(builder, src.shape, ndim),
                               strides=cgutils.unpack_tuple(builder, src.strides, ndim), itemsize=src.itemsize,
                               meminfo=None)
        return ary._getvalue()

    return sig, codegen
