"""Pure numerics of feedmon: covariance functions, the feed-drive model, least squares,
PL-LSSVM and the KRLS-T tracker. No I/O, no networking.

Submodules are imported on first use (PEP 562): ``from kernels.flags import EstimateFlag``
(what ``feedio.schema`` needs) does not load Numba; ``from kernels import KRLST`` loads
:mod:`kernels.krlst` and what it needs.
"""

from __future__ import annotations

import importlib

#: public name -> submodule that defines it
_EXPORTS = {
    "LSResult": "least_squares", "least_squares": "least_squares",
    "TuneResult": "likelihood", "log_marginal_likelihood": "likelihood", "tune": "likelihood",
    "PLLSSVMResult": "pl_lssvm", "pl_lssvm": "pl_lssvm",
    "SymmetricToeplitz": "toeplitz", "ToeplitzSolver": "toeplitz", "toeplitz_logdet": "levinson",
    "KRLST": "krlst", "Step": "krlst",
    "Kernel": "covariance", "LocallyPeriodic": "covariance", "Periodic": "covariance", "Product": "covariance",
    "SquaredExponential": "covariance",
    "EstimateFlag": "flags",
    "ParameterError": "errors",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
