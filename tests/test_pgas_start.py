"""Where the particle Gibbs chains start: the dispersal of the starts about their base path."""

import jax.numpy as jnp
import numpy as np
import pytest

import latentforce  # noqa: F401
from latentforce.inference.pgas_start import dispersal_cov


def _cov(eigenvalues, seed=0):
    """A covariance with these eigenvalues in a random orthonormal frame."""
    q = len(eigenvalues)
    Q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((q, q)))
    return Q @ np.diag(eigenvalues) @ Q.T, Q


@pytest.mark.parametrize("spread", [1.0, 2.0, 3.0])
def test_dispersal_is_the_posterior_with_the_data_information_divided_by_spread_squared(spread):
    # eigenvalues of C = (I + H)^-1 from a direction the data pin (1e-6 of the prior's
    # variance) to one they leave to the prior (1)
    c = np.array([1e-6, 1e-4, 1e-2, 0.3, 0.9, 1.0])
    C, Q = _cov(c)
    S = np.asarray(dispersal_cov(jnp.asarray(C), spread))
    H = np.linalg.inv(C) - np.eye(len(c))
    direct = np.linalg.inv(np.eye(len(c)) + H / spread**2)
    np.testing.assert_allclose(S, direct, rtol=1e-6, atol=1e-12)
    # per eigen-direction: 1 / (1 + h / s^2), h = 1/c - 1
    np.testing.assert_allclose(np.diag(Q.T @ S @ Q), 1.0 / (1.0 + (1.0 / c - 1.0) / spread**2), rtol=1e-6)


def test_pinned_directions_get_spread_posterior_sds_and_none_more_than_a_prior_sd():
    c = np.array([1e-8, 1e-5, 0.5, 1.0])
    C, Q = _cov(c, seed=1)
    S = np.asarray(dispersal_cov(jnp.asarray(C), 2.0))
    var = np.diag(Q.T @ S @ Q)
    # where the data pin the direction: spread^2 times the posterior variance, as before
    np.testing.assert_allclose(var[:2], 4.0 * c[:2], rtol=1e-4)
    # where the prior holds it: its prior variance, not four times it (the earlier 4 C)
    assert var[3] == pytest.approx(1.0, rel=1e-9)
    # in between, and always between the posterior and the prior (Loewner order)
    assert c[2] < var[2] < 1.0
    assert np.linalg.eigvalsh(np.eye(4) - S).min() > -1e-12
    assert np.linalg.eigvalsh(S - C).min() > -1e-12


def test_spread_one_starts_from_the_linearised_posterior_itself():
    C, _ = _cov(np.array([1e-7, 1e-3, 0.2, 1.0]), seed=2)
    np.testing.assert_allclose(np.asarray(dispersal_cov(jnp.asarray(C), 1.0)), C, rtol=1e-8, atol=1e-15)


def test_a_start_without_a_definite_mode_gets_a_moderate_diagonal_shape():
    """Where the filter's mode search fails (a rough likelihood: the 3-storey frame with a stiff cubic
    storey), the curvature at the point reached is no posterior's: its 1e-15 variances froze k3's
    walk and its unit ones spread starts by a factor of 40. The fallback is a diagonal whose log-space
    sds lie between a walk step (0.05) and a start spread (0.5)."""
    from latentforce.inference import pgas_mode

    C, _ = _cov([1e-15, 1.0, 1.0], seed=2)
    F = pgas_mode.fallback_cov(C)
    sd = np.sqrt(np.diag(F))
    assert np.all(F == np.diag(np.diag(F))) and np.all((0.05 <= sd) & (sd <= 0.5))
    np.linalg.cholesky(F)
    # a diagonal already in range is kept
    np.testing.assert_allclose(pgas_mode.fallback_cov(np.diag([0.01, 0.04])), np.diag([0.01, 0.04]))
