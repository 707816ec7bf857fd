"""Pure numerics of feedmon: covariance functions, the feed-drive model, least squares,
PL-LSSVM and the KRLS-T tracker. No I/O, no networking."""

from .covariance import Kernel, LocallyPeriodic, Periodic, Product, SquaredExponential
from .krlst import KRLST, Step
from .least_squares import LSResult, least_squares
from .likelihood import TuneResult, log_marginal_likelihood, tune
from .pl_lssvm import PLLSSVMResult, pl_lssvm
from .toeplitz import SymmetricToeplitz, ToeplitzSolver, toeplitz_logdet

__all__ = [
    "LSResult", "least_squares", "TuneResult", "log_marginal_likelihood", "tune", "PLLSSVMResult",
    "pl_lssvm", "SymmetricToeplitz", "ToeplitzSolver", "toeplitz_logdet",
    "KRLST", "Kernel", "LocallyPeriodic", "Periodic", "Product", "SquaredExponential", "Step"]
