"""latentforce.linalg: the LAPACK-free factorisations and solves, against NumPy (the module doc says
why they exist; that the samplers' programs hold no LAPACK call is checked in test_cli.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import latentforce  # noqa: F401
from latentforce import linalg


def _spd(rng, n, cond=1e3):
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (Q * np.geomspace(1.0, 1.0 / cond, n)) @ Q.T


@pytest.mark.parametrize("n", [1, 2, 5, 30])
def test_cholesky_matches_numpy(n):
    rng = np.random.default_rng(n)
    A = _spd(rng, n)
    L = np.asarray(linalg.cholesky(jnp.asarray(A)))
    np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=1e-10, atol=1e-12)
    assert np.all(np.triu(L, 1) == 0.0)
    # only the lower triangle is read
    junk = A + np.triu(rng.normal(size=(n, n)), 1)
    np.testing.assert_allclose(np.asarray(linalg.cholesky(jnp.asarray(junk))), L, rtol=1e-12, atol=1e-14)


def test_cholesky_batches_and_fails_like_jax():
    rng = np.random.default_rng(0)
    As = np.stack([_spd(rng, 4) for _ in range(3)])
    Ls = np.asarray(jax.vmap(linalg.cholesky)(jnp.asarray(As)))
    np.testing.assert_allclose(Ls, np.linalg.cholesky(As), rtol=1e-10, atol=1e-12)
    indefinite = np.diag([1.0, -1.0, 2.0])
    singular = np.ones((3, 3))
    for bad in (indefinite, singular, np.full((2, 2), np.nan)):
        assert np.all(np.isnan(np.asarray(linalg.cholesky(jnp.asarray(bad))))), bad


def test_psd_sqrt_of_rank_deficient_matrices():
    rng = np.random.default_rng(1)
    for n, r in [(5, 5), (5, 3), (6, 1), (3, 0)]:
        B = rng.normal(size=(n, r)) * np.geomspace(1.0, 1e-3, max(r, 1))[:r]
        A = B @ B.T
        A[0, 0] -= 1e-17  # round-off below zero in a null direction must not matter
        S = np.asarray(linalg.psd_sqrt(jnp.asarray(A)))
        assert np.all(np.isfinite(S))
        np.testing.assert_allclose(S @ S.T, A, atol=1e-12 * max(1.0, np.abs(A).max()))
    A = _spd(rng, 4)  # full rank: the Cholesky factor
    np.testing.assert_allclose(np.asarray(linalg.psd_sqrt(jnp.asarray(A))), np.linalg.cholesky(A), rtol=1e-10)


@pytest.mark.parametrize("rhs", [(6,), (6, 3)])
def test_triangular_and_cholesky_solves(rhs):
    rng = np.random.default_rng(2)
    A = _spd(rng, 6)
    L = np.linalg.cholesky(A)
    B = rng.normal(size=rhs)
    np.testing.assert_allclose(
        np.asarray(linalg.solve_lower(jnp.asarray(L), jnp.asarray(B))), np.linalg.solve(L, B), rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(linalg.solve_lower(jnp.asarray(L), jnp.asarray(B), transpose=True)),
        np.linalg.solve(L.T, B),
        rtol=1e-9,
        atol=1e-12,
    )
    np.testing.assert_allclose(
        np.asarray(linalg.cho_solve(jnp.asarray(L), jnp.asarray(B))), np.linalg.solve(A, B), rtol=1e-8, atol=1e-11
    )


def test_general_solve_pivots():
    rng = np.random.default_rng(3)
    # a zero leading pivot and a tiny one: without row exchanges these fail or lose all accuracy
    for A in (
        np.array([[0.0, 1.0], [1.0, 0.0]]),
        np.array([[1e-18, 1.0], [1.0, 1.0]]),
        rng.normal(size=(9, 9)),
        np.kron(rng.normal(size=(3, 3)), np.eye(3)) + np.kron(np.eye(3), rng.normal(size=(3, 3))),
    ):
        n = A.shape[0]
        for B in (rng.normal(size=n), rng.normal(size=(n, 4))):
            X = np.asarray(linalg.solve(jnp.asarray(A), jnp.asarray(B)))
            np.testing.assert_allclose(X, np.linalg.solve(A, B), rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(np.asarray(linalg.inv(jnp.asarray(A))), np.linalg.inv(A), rtol=1e-9, atol=1e-11)
    assert not np.all(np.isfinite(np.asarray(linalg.solve(jnp.ones((3, 3)), jnp.ones(3)))))


def test_derivatives_match_jax_linalg():
    """Forward and reverse mode through the loops agree with JAX's own (LAPACK-backed) rules."""
    rng = np.random.default_rng(4)
    A0, B = jnp.asarray(_spd(rng, 4, cond=10.0)), jnp.asarray(rng.normal(size=4))
    dA = jnp.asarray(0.01 * rng.normal(size=(4, 4)))

    def ours(t):
        A = A0 + t * (dA + dA.T)
        return (
            jnp.sum(linalg.cholesky(A)) + jnp.sum(linalg.solve(A, B)) + jnp.sum(linalg.cho_solve(linalg.cholesky(A), B))
        )

    def theirs(t):
        A = A0 + t * (dA + dA.T)
        return (
            jnp.sum(jnp.linalg.cholesky(A))
            + jnp.sum(jnp.linalg.solve(A, B))
            + jnp.sum(jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(A), True), B))
        )

    assert np.isfinite(float(theirs(0.1)))  # positive definite along the way
    for d in (lambda f: f, jax.jacfwd, jax.grad):
        np.testing.assert_allclose(float(d(ours)(0.1)), float(d(theirs)(0.1)), rtol=1e-8)


# The samplers' programs are checked for LAPACK calls on the CLI's runs of every sampling method
# (tests/test_cli.py, fixture ``lowered_programs`` of conftest.py), not on runs of their own here.


def test_log_abs_det_matches_numpy_and_pivots():
    """``log_abs_det`` against NumPy's slogdet on random, badly scaled (rows from 1e-12 to 1e3: the
    window move's Jacobians in mixed units) and pivot-needing matrices; a singular one gives -inf."""
    rng = np.random.default_rng(3)
    for n in (1, 3, 7):
        A = rng.normal(size=(n, n)) * np.logspace(-12, 3, n)[:, None]
        np.testing.assert_allclose(linalg.log_abs_det(jnp.asarray(A)), np.linalg.slogdet(A)[1], rtol=1e-12, atol=1e-10)
    swap = np.array([[0.0, 2.0, 1.0], [3.0, 1.0, 0.0], [1.0, 1.0, 5.0]])  # a zero first pivot
    np.testing.assert_allclose(linalg.log_abs_det(jnp.asarray(swap)), np.linalg.slogdet(swap)[1], rtol=1e-13)
    assert float(linalg.log_abs_det(jnp.asarray([[1.0, 2.0], [2.0, 4.0]]))) == -np.inf
