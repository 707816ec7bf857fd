"""Checks of a saved estimator snapshot before any of it reaches compiled code.

A tracker state file is input like any other: a crafted or damaged one must be refused with
a reason, never crash the monitor (the ``@njit`` core indexes its buffers with the saved
``order``, ``ist[I_N]`` and ``ist[I_HW]`` without bounds checks).

:func:`check_snapshot` compares a snapshot with two *templates*: the snapshots of a fresh
estimator with the same model before any sample and after one step
(:meth:`monitor.estimator.AxisEstimator.snapshot_templates`). The templates give every key,
shape and dtype and the hyperparameter values, so nothing here hard-codes the core's layout:

* the keys are exactly those of one template (no sample learned yet, or after a step);
* every array has the template's dtype and shape, and every float is finite;
* every entry that is not tracker state (hyperparameters, kernel, input dimension) equals the
  template's value: the model's hyperparameters;
* counters are integers in ``0 … COUNT_MAX``;
* the KRLS-T state is consistent (:func:`_check_krlst_state`): the invariants of the slot
  layout documented in :mod:`kernels._krlst_core`.
"""

from __future__ import annotations

import numpy as np

from kernels import _krlst_core as core

__all__ = ["StateError", "COUNT_MAX", "check_snapshot"]

#: largest counter a state may hold (samples learned, tracker steps): 2**53 − 1, >28,000 years at 10 kHz
COUNT_MAX = 2**53 - 1


class StateError(ValueError):
    """A saved state that cannot be used; the message says why."""


def _same_kind(arr: np.ndarray, like: np.ndarray) -> bool:
    if like.dtype.kind == "U":  # strings: any length up to the template's limit is checked by the reader
        return arr.dtype.kind == "U"
    return arr.dtype == like.dtype


def check_snapshot(snap: dict[str, np.ndarray], before: dict[str, np.ndarray],
                   after: dict[str, np.ndarray], *, counters: tuple[str, ...] = ()) -> None:
    """Raise :class:`StateError` unless ``snap`` is a valid snapshot like ``before`` (nothing learned)
    or ``after`` (after a step). ``counters`` name the 0-d integer entries that count something
    (checked to lie in ``0 … COUNT_MAX``, not compared with the template)."""
    keys = set(snap)
    if keys == set(after):
        template = after
    elif keys == set(before):
        template = before
    else:
        missing = sorted(set(before) - keys) or sorted(set(after) - keys)
        extra = sorted(keys - set(after))
        raise StateError("its entries do not match this model's tracker"
                         + (f"; missing {', '.join(missing)}" if missing else "")
                         + (f"; unexpected {', '.join(extra)}" if extra else ""))
    state_keys = set(after) - set(before)
    for key in sorted(template):
        arr, like = np.asarray(snap[key]), template[key]
        if not _same_kind(arr, like) or arr.shape != like.shape:
            raise StateError(f"{key!r} is {arr.dtype} {arr.shape}, expected {like.dtype} {like.shape}")
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise StateError(f"{key!r} holds non-finite values")
        if key in counters:
            value = int(arr)
            if not 0 <= value <= COUNT_MAX:
                raise StateError(f"{key!r} = {value} is outside 0…{COUNT_MAX}")
        elif key not in state_keys and not np.array_equal(arr, like):
            raise StateError(f"{key!r} is {arr.tolist()!r} but this model's is {like.tolist()!r} "
                             "(a state of other hyperparameters)")
    if template is after:
        prefix = _common_prefix(state_keys)
        _check_krlst_state({k[len(prefix):]: np.asarray(snap[k]) for k in state_keys},
                           {k[len(prefix):]: after[k] for k in state_keys}, budget=int(snap[prefix + "budget"]))


def _common_prefix(keys) -> str:
    """``"tracker."`` for ``{"tracker.X", "tracker.Q", …}``."""
    first = next(iter(keys))
    return first[: first.rfind(".") + 1]


def _check_krlst_state(s: dict[str, np.ndarray], like: dict[str, np.ndarray], budget: int) -> None:
    """Invariants of the KRLS-T slot layout (:mod:`kernels._krlst_core`, "Slots" and "Layout").

    Shapes are already those of the template ``like``; this checks the hyperparameters the core
    keeps in its state (``M``, λ, ``sn2``, ``ε_j``, ``1/Ts``: equal to the template's), the values it indexes with
    (dictionary size ``n ≤ M``, high-water mark ``hw``, the slot permutation ``order``),
    the pending/armed modes, that free slots are empty in ``Q``, ``Σ``, ``K`` (the core
    sums over ``[0, hw)`` relying on it) and that those matrices are symmetric (the core keeps
    them bitwise symmetric), and the signal-power accumulators.
    """
    ist, fst, order = s["ist"], s["fst"], s["order"]
    Q, Sig, K = s["Q"], s["Sigma"], s["K"]
    cap = order.shape[0]
    n, hw = int(ist[core.I_N]), int(ist[core.I_HW])
    if int(ist[core.I_M]) != budget or cap != budget + 1:
        raise StateError(f"tracker budget {int(ist[core.I_M])} (slots {cap}) does not match the model's {budget}")
    if not 0 <= n <= budget:
        raise StateError(f"tracker dictionary size {n} is outside 0…{budget}")
    if not n <= hw <= cap:
        raise StateError(f"tracker high-water mark {hw} is outside {n}…{cap}")
    if not np.array_equal(np.sort(order), np.arange(cap)):
        raise StateError(f"tracker slot order is not a permutation of 0…{cap - 1}")
    if n and int(order[:n].max()) >= hw:
        raise StateError("tracker dictionary uses a slot beyond its high-water mark")
    for name, slot, allowed in (("pending Q update", core.I_QPEND, (0, 1, 2)),
                                ("pending Σ update", core.I_SPEND, (0, 1)),
                                ("armed flag", core.I_ARMED, (0, 1))):
        if int(ist[slot]) not in allowed:
            raise StateError(f"tracker {name} is {int(ist[slot])}, expected one of {allowed}")
    if not 0 <= int(ist[core.I_STEPS]) <= COUNT_MAX:
        raise StateError(f"tracker step count {int(ist[core.I_STEPS])} is outside 0…{COUNT_MAX}")
    for name, slot in (("forgetting λ", core.F_LAM), ("noise ratio sn2", core.F_SN2), ("jitter ε_j", core.F_JIT),
                       ("1/Ts", core.F_INVTS)):
        if fst[slot] != like["fst"][slot]:
            raise StateError(f"tracker {name} is {float(fst[slot])!r} but this model's is {float(like['fst'][slot])!r}")
    free = order[n:]
    for name, m in (("Q", Q), ("Sigma", Sig), ("K", K)):
        if not np.array_equal(m, m.T):
            raise StateError(f"tracker matrix {name} is not symmetric")
        if free.size and (np.any(m[free, :] != 0.0) or np.any(m[:, free] != 0.0)):
            raise StateError(f"tracker matrix {name} has entries in free slots")
    if n and not np.all(np.diag(K)[order[:n]] > 0.0):
        raise StateError("tracker kernel matrix K has a non-positive diagonal")
    num, den, s02 = float(fst[core.F_NUM]), float(fst[core.F_DEN]), float(fst[core.F_S02])
    if num < 0.0 or s02 < 0.0 or den < (1.0 if n else 0.0):
        raise StateError(f"tracker signal-power accumulators are impossible (num {num}, den {den}, s0² {s02})")
