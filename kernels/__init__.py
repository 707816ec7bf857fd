"""Pure numerics of feedmon: covariance functions, the feed-drive model, least squares,
PL-LSSVM and the KRLS-T tracker. No I/O, no networking."""

from .covariance import Kernel, LocallyPeriodic, Periodic, Product, SquaredExponential
from .krlst import KRLST, Step

__all__ = ["KRLST", "Kernel", "LocallyPeriodic", "Periodic", "Product", "SquaredExponential", "Step"]
