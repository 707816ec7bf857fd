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
* the KRLS-T state is consistent (:func:`_check_krlst_state`): the invariants of the core's
  layout, checked by :func:`kernels._krlst_core.validate_state` (one definition, next to the layout).
"""

from __future__ import annotations

import numpy as np

from kernels import _krlst_core as core
from kernels import disturbance_search as ds
from kernels.krlst import KRLST

__all__ = ["StateError", "COUNT_MAX", "CHOICE", "check_snapshot", "choice_array", "choice_of_array"]

#: the state entry of the disturbance model the online search had chosen
CHOICE = "estimator.choice"
_KINDS = ("time", "periodic", "spindle")

#: largest counter a state may hold (samples learned, tracker steps): 2**53 − 1, >28,000 years at 10 kHz
COUNT_MAX = 2**53 - 1


class StateError(ValueError):
    """A saved state that cannot be used; the message says why."""


def _same_kind(arr: np.ndarray, like: np.ndarray) -> bool:
    if like.dtype.kind == "U":  # strings: any length up to the template's limit is checked by the reader
        return arr.dtype.kind == "U"
    return arr.dtype == like.dtype


def check_snapshot(snap: dict[str, np.ndarray], before: dict[str, np.ndarray],
                   after: dict[str, np.ndarray], *, counters: tuple[str, ...] = (),
                   tracker_prefix: str = "tracker.") -> None:
    """Raise :class:`StateError` unless ``snap`` is a valid snapshot like ``before`` (nothing learned)
    or ``after`` (after a step). ``counters`` name the 0-d integer entries that count something
    (checked to lie in ``0 … COUNT_MAX``, not compared with the template); the KRLS-T state is the
    entries under ``tracker_prefix`` (other state entries, e.g. the online β, are checked by their
    owners when restored)."""
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
        prefix = tracker_prefix
        _check_krlst_state({k[len(prefix):]: np.asarray(snap[k]) for k in snap if k.startswith(prefix)},
                           after[prefix + "fst"], budget=int(snap[prefix + "budget"]))


def _check_krlst_state(tracker: dict[str, np.ndarray], like_fst: np.ndarray, budget: int) -> None:
    """The KRLS-T part of a snapshot (its keys without the ``tracker.`` prefix): rebuilt by
    :meth:`kernels.krlst.KRLST.restore`, which checks shapes against the core's ``new_state`` and the
    state's own invariants (:func:`kernels._krlst_core.validate_state`: the indices the compiled core
    uses without bounds checks, free slots, triangles, modes, accumulators) — one definition, next
    to the layout — then the hyperparameters the state keeps inside (``M``, λ, ``sn2``, ``ε_j``,
    ``1/Ts``) against the template's."""
    try:
        restored = KRLST.restore(tracker)
    except ValueError as exc:
        raise StateError(f"tracker {exc}") from None
    st = restored.core_state(np.zeros(int(tracker["dim"])))
    if int(st.ist[core.I_M]) != budget:
        raise StateError(f"tracker budget {int(st.ist[core.I_M])} does not match the model's {budget}")
    if not 0 <= int(st.ist[core.I_STEPS]) <= COUNT_MAX:
        raise StateError(f"tracker step count {int(st.ist[core.I_STEPS])} is outside 0…{COUNT_MAX}")
    for name, slot in (("forgetting λ", core.F_LAM), ("noise ratio sn2", core.F_SN2), ("jitter ε_j", core.F_JIT),
                       ("1/Ts", core.F_INVTS)):
        if st.fst[slot] != like_fst[slot]:
            raise StateError(f"tracker {name} is {float(st.fst[slot])!r} but this model's is {float(like_fst[slot])!r}")
    _check_posterior(restored)


#: how far a restored state may be from the identities that hold for every state the tracker writes
#: (generous: the refined recursion keeps ‖Q K_D − I‖ ~1e-8; a damaged or crafted state is far off)
K_TOL, INVERSE_TOL, SIGMA_TOL, MU_MAX = 1e-9, 1e-3, 1e-6, 1e6


def _check_posterior(tr: KRLST) -> None:
    """The numbers of the state against what they must be: ``K_D`` is the kernel of the dictionary
    (+ ``ε_j I``), ``Q`` its inverse, ``Σ`` a covariance between 0 and the prior ``K_D``
    (back-to-the-prior forgetting never leaves that range) and ``μ`` of a plausible size (m/s).
    A state that passes the layout checks but holds other numbers would feed NaN/inf through
    every later step; it is refused instead."""
    if tr.size == 0:
        return
    K = tr.K
    with np.errstate(over="ignore", invalid="ignore"):  # a damaged dictionary (1e300 s) is refused below
        ref = tr.kernel(tr.dictionary) + tr.jitter * np.eye(tr.size)
    if not np.max(np.abs(K - ref)) <= K_TOL:
        raise StateError("tracker kernel matrix K_D is not the kernel of its dictionary")
    if not tr.inverse_error() <= INVERSE_TOL:
        raise StateError(f"tracker Q is not the inverse of K_D (max |Q K_D − I| = {tr.inverse_error():.3g})")
    S = tr.Sigma
    if not np.max(np.abs(S - S.T)) <= SIGMA_TOL:
        raise StateError("tracker posterior covariance Σ is not symmetric")
    lo = np.linalg.eigvalsh(0.5 * (S + S.T))
    hi = np.linalg.eigvalsh(0.5 * ((K - S) + (K - S).T))
    if not (lo.min() >= -SIGMA_TOL and hi.min() >= -SIGMA_TOL):
        raise StateError("tracker posterior covariance Σ is not between 0 and the prior K_D")
    if not np.max(np.abs(tr.mu)) <= MU_MAX:
        raise StateError(f"tracker posterior mean μ is implausibly large (|μ| up to {np.max(np.abs(tr.mu)):.3g} m/s)")


def choice_array(c: ds.TrackerChoice) -> np.ndarray:
    """A disturbance model as the plain array a state file holds."""
    return np.array([_KINDS.index(c.kind), c.sigma1, c.sigma2, c.period, c.teeth, c.gamma, c.forgetting,
                     float(c.zero_mean)])


def choice_of_array(a) -> ds.TrackerChoice:
    """Inverse of :func:`choice_array`, every value checked against the ranges a model file allows for it
    (:class:`StateError` naming the value)."""
    a = np.asarray(a)
    if a.shape != (8,) or a.dtype.kind != "f" or not np.isfinite(a).all():
        raise StateError(f"{CHOICE!r} must be 8 finite numbers, got {a.dtype} {a.shape}")
    kind, s1, s2, period, teeth, gamma, lam, zero_mean = (float(x) for x in a)
    checks = (("kind", kind in (0.0, 1.0, 2.0)), ("sigma1", 1e-6 <= s1 <= 1e6), ("sigma2", 1e-3 <= s2 <= 1e3),
              ("period", kind != 1.0 or 1e-6 <= period <= 1e6), ("teeth", teeth == int(teeth) and 1 <= teeth <= 1000),
              ("gamma", 1e-4 <= gamma <= 1e8), ("forgetting", 0.5 <= lam <= 1.0), ("zero_mean", zero_mean in (0.0, 1.0)))
    for name, ok in checks:
        if not ok:
            names = ("kind", "sigma1", "sigma2", "period", "teeth", "gamma", "forgetting", "zero_mean")
            raise StateError(f"{CHOICE!r}: {name} {dict(zip(names, a.tolist()))[name]!r} is outside what a model "
                             "file allows")
    return ds.TrackerChoice(_KINDS[int(kind)], sigma1=s1, sigma2=s2, period=period, teeth=int(teeth), gamma=gamma,
                            forgetting=lam, zero_mean=bool(zero_mean))
