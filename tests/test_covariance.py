"""Covariance functions (method §5): one formula, NumPy and @njit paths agree, PD, conventions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kernels import Kernel, LocallyPeriodic, Periodic, Product, SquaredExponential
from kernels.covariance import kernel_row, kernel_row_at, kernel_value, kernel_value_at

KERNELS = [
    SquaredExponential(0.7),
    Periodic(0.495, 1 / 55),
    LocallyPeriodic(1.2, 0.495, 1 / 55),
    Product(LocallyPeriodic(0.5, 0.8, 0.3, dims=0), SquaredExponential(1.5, dims=slice(1, 3))),
]


def _inputs(kernel: Kernel, n: int, rng) -> np.ndarray:
    d = 3 if isinstance(kernel, Product) else (2 if isinstance(kernel, SquaredExponential) else 1)
    return rng.uniform(-2.0, 2.0, (n, d))


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: type(k).__name__)
def test_numpy_matrix_equals_njit_row(kernel):
    rng = np.random.default_rng(0)
    X = _inputs(kernel, 40, rng)
    K = kernel(X)
    kinds, params, cols = kernel.spec()
    out = np.empty(len(X))
    for j in range(len(X)):
        kernel_row(kinds, params, cols, X, len(X), X[j], out)
        np.testing.assert_allclose(out, K[:, j], rtol=1e-13, atol=1e-15)
        assert kernel_value(kinds, params, cols, X[j], X[j]) == 1.0


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: type(k).__name__)
def test_njit_entry_points_agree_bitwise(kernel):
    # kernel_row / kernel_row_at (factor-outer loops) and kernel_value / kernel_value_at
    # (per pair) evaluate the same product ((1·f0)·f1)·… of the same compiled formulas
    rng = np.random.default_rng(2)
    X = _inputs(kernel, 30, rng)
    x = _inputs(kernel, 1, rng)[0]
    kinds, params, cols = kernel.spec()
    row = np.empty(len(X))
    kernel_row(kinds, params, cols, X, len(X), x, row)
    idx = rng.permutation(len(X))[:20].astype(np.int64)
    picked = np.full(len(X), -7.0)
    kernel_row_at(kinds, params, cols, X, idx, len(idx), x, picked)
    for i in range(len(X)):
        v = kernel_value(kinds, params, cols, X[i], x)
        assert kernel_value_at(kinds, params, cols, X, i, x) == v
        assert row[i] == v
        assert picked[i] == (v if i in idx else -7.0)


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: type(k).__name__)
def test_unit_diagonal(kernel):
    X = _inputs(kernel, 10, np.random.default_rng(1))
    # the NumPy SE path expands ||a−b||² = |a|²+|b|²−2a·b, so its diagonal is 1 to rounding;
    # the @njit path and diag() are exact
    np.testing.assert_allclose(np.diag(kernel(X)), 1.0, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(kernel.diag(X), 1.0)
    kinds, params, cols = kernel.spec()
    assert all(kernel_value(kinds, params, cols, x, x) == 1.0 for x in X)


def test_locally_periodic_formula_and_periodicity():
    s1, s2, psi = 1.2, 0.495, 1 / 55
    k = LocallyPeriodic(s1, s2, psi)
    d = np.linspace(-0.3, 0.3, 101)
    expected = np.exp(-d**2 / (2 * s1**2)) * np.exp(-np.sin(np.pi * d / psi) ** 2 / (2 * s2**2))
    np.testing.assert_allclose(k.lag(d), expected, rtol=1e-14)
    np.testing.assert_allclose(k(d[:, None], np.zeros((1, 1)))[:, 0], expected, rtol=1e-14)
    p = Periodic(s2, psi)
    t = np.linspace(0, 1, 37)
    np.testing.assert_allclose(p.lag(t + 7 * psi), p.lag(t), atol=1e-12)


def test_sklearn_expsinesquared_convention():
    # scikit-learn ExpSineSquared: exp(-2 sin²(π d / p) / ℓ²); method §5: ℓ = 2 σ2
    s2, psi = 0.495, 1 / 55
    ell = 2 * s2
    d = np.linspace(-0.1, 0.1, 51)
    sklearn_form = np.exp(-2.0 * np.sin(np.pi * np.abs(d) / psi) ** 2 / ell**2)
    np.testing.assert_allclose(Periodic(s2, psi).lag(d), sklearn_form, rtol=1e-14)


def test_se_formula():
    ell = 0.7
    X1 = np.array([[0.0, 0.0], [1.0, 2.0]])
    X2 = np.array([[0.5, -1.0]])
    expected = np.exp(-np.sum((X1 - X2) ** 2, 1) / (2 * ell**2))
    np.testing.assert_allclose(SquaredExponential(ell)(X1, X2)[:, 0], expected, rtol=1e-14)


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: type(k).__name__)
def test_to_dict_round_trip(kernel):
    again = Kernel.from_dict(kernel.to_dict())
    assert again == kernel
    X = _inputs(kernel, 5, np.random.default_rng(2))
    np.testing.assert_array_equal(again(X), kernel(X))


@pytest.mark.parametrize(
    "make",
    [
        lambda: SquaredExponential(0.0),
        lambda: SquaredExponential(-1.0),
        lambda: Periodic(0.5, math.inf),
        lambda: LocallyPeriodic(math.nan, 0.5, 0.1),
        lambda: LocallyPeriodic(1.0, 0.5, 0.0),
        lambda: Product(SquaredExponential(1.0)),
        lambda: Kernel.from_dict({"type": "locally_periodic", "sigma1": 1.0}),
        lambda: Kernel.from_dict({"type": "nope"}),
    ],
)
def test_bad_parameters_rejected(make):
    with pytest.raises(ValueError):
        make()


# -- positive definiteness (hypothesis) ---------------------------------------------------

pos = st.floats(min_value=0.05, max_value=5.0, allow_nan=False, allow_infinity=False)


def _assert_pd(K: np.ndarray) -> None:
    n = K.shape[0]
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-15)
    lam_min = np.linalg.eigvalsh(K + 1e-9 * np.eye(n)).min()
    assert lam_min >= -1e-9 * n
    np.linalg.cholesky(K + 1e-8 * np.eye(n))


_pd_settings = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@_pd_settings
@given(ell=pos, seed=st.integers(0, 2**32 - 1), n=st.integers(2, 30))
def test_pd_squared_exponential(ell, seed, n):
    X = np.random.default_rng(seed).uniform(-3, 3, (n, 2))
    _assert_pd(SquaredExponential(ell)(X))


@_pd_settings
@given(s2=pos, period=pos, seed=st.integers(0, 2**32 - 1), n=st.integers(2, 30))
def test_pd_periodic(s2, period, seed, n):
    t = np.random.default_rng(seed).uniform(-5, 5, n)
    _assert_pd(Periodic(s2, period)(t))


@_pd_settings
@given(s1=pos, s2=pos, period=pos, seed=st.integers(0, 2**32 - 1), n=st.integers(2, 30))
def test_pd_locally_periodic(s1, s2, period, seed, n):
    t = np.random.default_rng(seed).uniform(-5, 5, n)
    _assert_pd(LocallyPeriodic(s1, s2, period)(t))


@_pd_settings
@given(s1=pos, s2=pos, period=pos, ell=pos, seed=st.integers(0, 2**32 - 1), n=st.integers(2, 30))
def test_pd_product(s1, s2, period, ell, seed, n):
    X = np.random.default_rng(seed).uniform(-3, 3, (n, 3))
    k = LocallyPeriodic(s1, s2, period, dims=0) * SquaredExponential(ell, dims=slice(1, 3))
    _assert_pd(k(X))


def test_zero_mean_locally_periodic_is_one_factor_for_batch_lag_and_compiled_paths():
    """The zero-mean locally periodic kernel: k(0) = 1, its mean over a period removed (the batch matrix
    is positive semi-definite and a long window of it averages to ~0 per period), the same numbers from
    the batch matrix, the Toeplitz lag, the compiled value and the compiled phased row, and c0 = e^−a I0(a)."""
    from scipy.special import i0e

    from kernels.covariance import (
        ZeroMeanLocallyPeriodic,
        kernel_phases,
        kernel_row_phased,
        kernel_value,
    )

    k = ZeroMeanLocallyPeriodic(0.4, 0.6, 0.05)
    assert k.c0 == pytest.approx(i0e(1.0 / (4 * 0.6**2)), rel=1e-14)
    t = np.linspace(0.0, 1.0, 301)
    K = k(t)
    assert K[0, 0] == 1.0 and np.linalg.eigvalsh(K).min() > -1e-10
    np.testing.assert_allclose(K[0], k.lag(t), rtol=1e-13, atol=1e-15)
    # a sharp SE window sees whole periods: the periodic factor's mean is gone
    flat = ZeroMeanLocallyPeriodic(1e6, 0.6, 0.05)
    assert abs(np.mean(flat.lag(np.linspace(0.0, 0.05, 2001)[:-1]))) < 1e-12
    kinds, params, cols = k.spec()
    X = np.ascontiguousarray(t[::10]).reshape(-1, 1)   # C order, as the tracker's: no extra compilation
    x = np.array([0.123])
    ref = k(X, x)[:, 0]
    got = np.array([kernel_value(kinds, params, cols, X[i], x) for i in range(X.shape[0])])
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)
    Ph = np.zeros((X.shape[0], 2))
    for i in range(X.shape[0]):
        kernel_phases(kinds, params, cols, X[i], Ph[i])
    xph = np.zeros(2)
    kernel_phases(kinds, params, cols, x, xph)
    row = np.zeros(X.shape[0])
    kernel_row_phased(kinds, params, cols, X, Ph, np.ones(X.shape[0]), 0, X.shape[0], x, xph, row)
    np.testing.assert_allclose(row, ref, rtol=1e-12, atol=1e-14)
