"""Kalman filter and RTS smoother against the dense Gaussian answer."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import latentforce  # noqa: F401
from latentforce.compile import jit
from latentforce.inference.kalman import (
    kalman_filter,
    kalman_smoother,
    log_likelihood,
    sample_smoothed_trajectory,
)
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.systems import LinearSystem


def dense_gaussian(A, Q, H, R, m0, P0, y, mask):
    """Joint Gaussian of x_{1:T} and the observed entries of y, built densely."""
    T, n = y.shape[0], A.shape[0]
    means = [m0]
    covs = [P0]
    for _ in range(1, T):
        means.append(A @ means[-1])
        covs.append(A @ covs[-1] @ A.T + Q)
    mx = np.concatenate(means)
    Sx = np.zeros((T * n, T * n))
    for t in range(T):
        Sx[t * n : (t + 1) * n, t * n : (t + 1) * n] = covs[t]
        for s in range(t):  # Cov(x_t, x_s) = A^{t-s} P_s
            C = np.linalg.matrix_power(A, t - s) @ covs[s]
            Sx[t * n : (t + 1) * n, s * n : (s + 1) * n] = C
            Sx[s * n : (s + 1) * n, t * n : (t + 1) * n] = C.T
    Hb = np.kron(np.eye(T), H)
    Rb = np.kron(np.eye(T), R)
    keep = mask.reshape(-1)
    Hb, Rb, yv = Hb[keep], Rb[np.ix_(keep, keep)], y.reshape(-1)[keep]
    Sy = Hb @ Sx @ Hb.T + Rb
    ll = stats.multivariate_normal(Hb @ mx, Sy).logpdf(yv)
    K = Sx @ Hb.T @ np.linalg.inv(Sy)
    post_mean = mx + K @ (yv - Hb @ mx)
    post_cov = Sx - K @ Hb @ Sx
    return ll, post_mean.reshape(T, n), np.array([post_cov[t * n : (t + 1) * n, t * n : (t + 1) * n] for t in range(T)])


def oma_like_model(noise=(1e-2, 5e-2)):
    model = LatentForceModel(
        LinearSystem(),
        Matern(1),
        [Sensor("displacement", 0, noise[0]), Sensor("acceleration", 0, noise[1])],
    )
    params = dict(m=2.0, c=0.3, k=20.0, force_variance=4.0, force_lengthscale=0.8)
    return model, params


@pytest.mark.parametrize("with_missing", [False, True])
def test_filter_smoother_match_dense_gaussian(with_missing):
    model, params = oma_like_model()
    dt, T = 0.1, 25
    A, Q = model.discretise(params, dt)
    H, R = model.observation(params)
    m0, P0 = model.stationary_initial(params)
    rng = np.random.default_rng(1)
    y = rng.normal(size=(T, 2))
    mask = np.ones((T, 2), bool)
    if with_missing:
        mask[rng.random((T, 2)) < 0.3] = False
        mask[3] = False  # a step with nothing observed
        y = np.where(mask, y, np.nan)
    ll_dense, mean_dense, cov_dense = dense_gaussian(*map(np.asarray, (A, Q, H, R, m0, P0)), np.nan_to_num(y), mask)
    sm = kalman_smoother(A, Q, H, R, m0, P0, jnp.asarray(y), jnp.asarray(mask))
    ll = log_likelihood(A, Q, H, R, m0, P0, jnp.asarray(y), jnp.asarray(mask))
    assert np.isclose(float(sm.log_likelihood), ll_dense, rtol=1e-9, atol=1e-9)
    assert np.isclose(float(ll), ll_dense, rtol=1e-9, atol=1e-9)
    scale = np.sqrt(np.diagonal(cov_dense, axis1=1, axis2=2)).max(axis=0)
    np.testing.assert_allclose(np.asarray(sm.means) / scale, mean_dense / scale, atol=1e-8)
    np.testing.assert_allclose(np.asarray(sm.covs), cov_dense, rtol=1e-6, atol=1e-10 * np.abs(cov_dense).max())


def test_filter_is_causal_and_matches_dense_filtering_at_last_step():
    model, params = oma_like_model()
    A, Q = model.discretise(params, 0.1)
    H, R = model.observation(params)
    m0, P0 = model.stationary_initial(params)
    y = np.random.default_rng(2).normal(size=(12, 2))
    filt = kalman_filter(A, Q, H, R, m0, P0, jnp.asarray(y))
    _, mean_dense, _ = dense_gaussian(*map(np.asarray, (A, Q, H, R, m0, P0)), y, np.ones_like(y, bool))
    # the filtered and smoothed moments coincide at the final step
    np.testing.assert_allclose(np.asarray(filt.means[-1]), mean_dense[-1], rtol=1e-7, atol=1e-9)


def test_stable_for_stiff_lightly_damped_long_lengthscale():
    """The paper's OMA system (zeta ~ 0.006) with a long lengthscale over a long record: no NaN."""
    model = LatentForceModel(LinearSystem(), Matern(1), [Sensor("displacement", 0, 1e-4)])
    params = dict(m=2000.0, c=5.0, k=100.0, force_variance=1e6, force_lengthscale=500.0)
    A, Q = model.discretise(params, 0.5)
    H, R = model.observation(params)
    m0, P0 = model.stationary_initial(params)
    y = jnp.asarray(np.random.default_rng(0).normal(size=(4096, 1)) * 1e-2)
    sm = kalman_smoother(A, Q, H, R, m0, P0, y)
    assert np.isfinite(float(sm.log_likelihood))
    assert np.all(np.isfinite(np.asarray(sm.means))) and np.all(np.isfinite(np.asarray(sm.covs)))
    assert np.all(np.linalg.eigvalsh(np.asarray(sm.covs)) > -1e-8 * np.abs(np.asarray(sm.covs)).max())


def test_backward_sampling_matches_smoother_moments():
    model, params = oma_like_model()
    A, Q = model.discretise(params, 0.1)
    H, R = model.observation(params)
    m0, P0 = model.stationary_initial(params)
    y = jnp.asarray(np.random.default_rng(3).normal(size=(30, 2)))
    filt = kalman_filter(A, Q, H, R, m0, P0, y)
    sm = kalman_smoother(A, Q, H, R, m0, P0, y)
    n_draws = 4000
    keys = jax.random.split(jax.random.key(0), n_draws)
    draws = jit(jax.vmap(lambda k: sample_smoothed_trajectory(k, A, Q, filt)))(keys)
    sd = np.sqrt(np.diagonal(np.asarray(sm.covs), axis1=1, axis2=2))
    z = (np.asarray(draws.mean(0)) - np.asarray(sm.means)) / (sd / np.sqrt(n_draws))
    assert np.abs(z).max() < 5.0  # within 5 Monte-Carlo standard errors everywhere
    ratio = np.asarray(draws.std(0)) / sd
    assert np.all(np.abs(ratio - 1) < 5 * np.sqrt(1 / (2 * n_draws)) + 0.01)


@pytest.mark.parametrize("lengthscale,n_obs", [(0.8, 2), (50.0, 1)])
def test_steady_state_shortcut_is_exact(lengthscale, n_obs):
    """The cut-short covariance recursion gives the full filter's log-likelihood."""
    from latentforce.inference.kalman import log_likelihood_complete

    sensors = [Sensor("displacement", 0, 1e-2), Sensor("acceleration", 0, 5e-2)][:n_obs]
    model = LatentForceModel(LinearSystem(), Matern(1), sensors)
    params = dict(m=2.0, c=0.3, k=20.0, force_variance=4.0, force_lengthscale=lengthscale)
    A, Q = model.discretise(params, 0.1)
    H, R = model.observation(params)
    m0, P0 = model.stationary_initial(params)
    y = jnp.asarray(np.random.default_rng(4).normal(size=(3000, n_obs)))
    full = float(log_likelihood(A, Q, H, R, m0, P0, y))
    fast = float(log_likelihood_complete(A, Q, H, R, m0, P0, y))
    assert np.isclose(fast, full, rtol=1e-10, atol=1e-8)
    grad_full = jax.grad(lambda a: log_likelihood(a * A, Q, H, R, m0, P0, y))(1.0)
    assert np.isfinite(float(grad_full))


def test_mdof_filter_smoother_match_dense_gaussian():
    M = jnp.diag(jnp.array([1.0, 2.0]))
    K = jnp.array([[30.0, -10.0], [-10.0, 10.0]])
    model = LatentForceModel(
        LinearSystem(ndof=2, force_dofs=(0, 1)),
        Matern(1),
        [Sensor("acceleration", 0, 0.1), Sensor("displacement", 1, 0.01)],
    )
    params = dict(M=M, C=0.02 * K + 0.1 * M, K=K, force_variance=2.0, force_lengthscale=0.5)
    A, Q = model.discretise(params, 0.1)
    H, R = model.observation(params)
    m0, P0 = model.stationary_initial(params)
    y = np.random.default_rng(5).normal(size=(15, 2))
    mask = np.ones_like(y, bool)
    ll_dense, mean_dense, cov_dense = dense_gaussian(*map(np.asarray, (A, Q, H, R, m0, P0)), y, mask)
    sm = kalman_smoother(A, Q, H, R, m0, P0, jnp.asarray(y))
    assert np.isclose(float(sm.log_likelihood), ll_dense, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(sm.covs), cov_dense, rtol=1e-6, atol=1e-10 * np.abs(cov_dense).max())
