r"""Kalman filter, RTS smoother and the exact log-likelihood of a linear-Gaussian model.

Model (column states, ``x_next = A @ x``)

.. math::
    x_1 \sim N(m_0, P_0), \qquad x_{t+1} = A x_t + q_t,\; q_t \sim N(0, Q),
    \qquad y_t = H x_t + r_t,\; r_t \sim N(0, R).

``m0, P0`` is the prior of the *first sampled* state (no prediction step
before the first update). The log-likelihood is the prediction-error
decomposition, i.e. minus the energy function :math:`\varphi_T` of Eq. (24-26)
of ISMA 2018 (Särkkä 2013, Eq. 12.11).

Missing samples: ``mask[t, i] = False`` removes channel ``i`` at step ``t``
from the update, without changing shapes (one compiled program for every
missingness pattern). NaN in ``y`` where the mask is false is harmless.

Numerics: sensor noises are independent (diagonal ``R``), so channels are
assimilated one scalar at a time: no matrix factorisation in the forward
pass, symmetrisation after every update, all in float64.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from latentforce.linalg import psd_sqrt, solve, symmetrise

_LOG_2PI = math.log(2.0 * math.pi)


class FilterResult(NamedTuple):
    """Filtered moments ``p(x_t | y_{1:t})`` and one-step predictions ``p(x_{t+1} | y_{1:t})``."""

    means: Float[Array, "T n"]
    covs: Float[Array, "T n n"]
    pred_means: Float[Array, "T n"]
    pred_covs: Float[Array, "T n n"]
    log_likelihood: Float[Array, ""]


class SmootherResult(NamedTuple):
    """Smoothed moments ``p(x_t | y_{1:T})``."""

    means: Float[Array, "T n"]
    covs: Float[Array, "T n n"]
    log_likelihood: Float[Array, ""]


def update_channels(m, P, H, R, y, mask):
    """Kalman update of ``N(m, P)`` with ``y``, one channel at a time; returns the filtered
    moments and each channel's squared standardised prediction error ``v^2 / s`` and ``log s``.

    The sensors' noises are independent (``R`` diagonal; only its diagonal
    is read), so the channels are assimilated one scalar at a time
    (Särkkä 2013, §4.3 remark; Bierman 1977). Exactly equivalent to the joint
    update, it needs no matrix factorisation: a handful of fused vector ops
    per channel, which is what makes the recursion cheap when vmapped over
    chains. An unobserved channel is skipped by zeroing its gain (its terms
    are returned all the same: mask them).
    """
    r = jnp.diagonal(R)
    z2, log_s = [], []
    for i in range(H.shape[0]):
        h = H[i]
        Ph = P @ h
        s = h @ Ph + r[i]
        v = y[i] - h @ m
        k = jnp.where(mask[i], Ph / s, 0.0)
        m = m + k * v
        P = symmetrise(P - s * jnp.outer(k, k))
        z2.append(v * v / s)
        log_s.append(jnp.log(s))
    return m, P, jnp.stack(z2), jnp.stack(log_s)


def _update(m, P, H, R, y, mask):
    """:func:`update_channels` with log p(y_t | y_{1:t-1}) over the observed channels."""
    m, P, z2, log_s = update_channels(m, P, H, R, y, mask)
    return m, P, jnp.sum(jnp.where(mask, -0.5 * (z2 + log_s + _LOG_2PI), 0.0))


def kalman_filter(
    A: Float[Array, "n n"],
    Q: Float[Array, "n n"],
    H: Float[Array, "d n"],
    R: Float[Array, "d d"],
    m0: Float[Array, " n"],
    P0: Float[Array, "n n"],
    y: Float[Array, "T d"],
    mask: Bool[Array, "T d"] | None = None,
) -> FilterResult:
    """Kalman filter as a ``lax.scan``; see the module docstring for the model."""
    if mask is None:
        mask = jnp.isfinite(y)
    y = jnp.where(mask, y, 0.0)

    def _step(carry, inputs):
        m, P, ll = carry
        y_t, mask_t = inputs
        m_f, P_f, ll_t = _update(m, P, H, R, y_t, mask_t)
        m_p = A @ m_f
        P_p = symmetrise(A @ P_f @ A.T + Q)
        return (m_p, P_p, ll + ll_t), (m_f, P_f, m_p, P_p)

    (_, _, ll), (ms, Ps, mps, Pps) = jax.lax.scan(_step, (m0, P0, jnp.zeros(())), (y, mask))
    return FilterResult(ms, Ps, mps, Pps, ll)


def log_likelihood(A, Q, H, R, m0, P0, y, mask=None) -> Float[Array, ""]:
    """Exact log-likelihood ``log p(y_{1:T})``.

    The filter's own value: under ``jit`` the stored moments it does not need
    are dropped by dead-code elimination, so this costs no more memory than a
    separate likelihood-only recursion.
    """
    return kalman_filter(A, Q, H, R, m0, P0, y, mask).log_likelihood


def rts_smoother(A: Float[Array, "n n"], filtered: FilterResult) -> SmootherResult:
    r"""Rauch-Tung-Striebel smoother, a reverse ``lax.scan`` (Särkkä 2013, Thm 8.2).

    The gain :math:`G_t = P_t A^T (P^-_{t+1})^{-1}` is computed with a linear
    solve against the symmetric predicted covariance rather than an explicit
    inverse; the predicted covariance is full rank whenever the force noise
    reaches every state, which the augmented model guarantees.
    """

    def _step(carry, inputs):
        m_next, P_next = carry
        m_f, P_f, m_p, P_p = inputs
        G = solve(P_p, A @ P_f).T
        m_s = m_f + G @ (m_next - m_p)
        P_s = symmetrise(P_f + G @ (P_next - P_p) @ G.T)
        return (m_s, P_s), (m_s, P_s)

    last = (filtered.means[-1], filtered.covs[-1])
    inputs = (filtered.means[:-1], filtered.covs[:-1], filtered.pred_means[:-1], filtered.pred_covs[:-1])
    _, (ms, Ps) = jax.lax.scan(_step, last, inputs, reverse=True)
    means = jnp.concatenate([ms, filtered.means[-1:]], axis=0)
    covs = jnp.concatenate([Ps, filtered.covs[-1:]], axis=0)
    return SmootherResult(means, covs, filtered.log_likelihood)


def kalman_smoother(A, Q, H, R, m0, P0, y, mask=None) -> SmootherResult:
    """Filter then smooth; returns smoothed moments and the exact log-likelihood."""
    return rts_smoother(A, kalman_filter(A, Q, H, R, m0, P0, y, mask))


def sample_smoothed_trajectory(key, A, Q, filtered: FilterResult) -> Float[Array, "T n"]:
    r"""One draw of :math:`x_{1:T} \sim p(x_{1:T} | y_{1:T})` by backward sampling.

    Forward-filtering backward-sampling (Carter & Kohn 1994): :math:`x_T \sim N(m_T, P_T)`, then
    :math:`x_t | x_{t+1} \sim N(m_t + G_t(x_{t+1} - m^-_{t+1}), P_t - G_t P^-_{t+1} G_t^T)`.
    """
    T, n = filtered.means.shape
    keys = jax.random.split(key, T)

    x_last = _gaussian_draw(keys[-1], filtered.means[-1], filtered.covs[-1])

    def _step(x_next, inputs):
        k, m_f, P_f, m_p, P_p = inputs
        G = solve(P_p, A @ P_f).T
        mean = m_f + G @ (x_next - m_p)
        x = _gaussian_draw(k, mean, P_f - G @ P_p @ G.T)
        return x, x

    inputs = (keys[:-1], filtered.means[:-1], filtered.covs[:-1], filtered.pred_means[:-1], filtered.pred_covs[:-1])
    _, xs = jax.lax.scan(_step, x_last, inputs, reverse=True)
    return jnp.concatenate([xs, x_last[None]], axis=0)


def _gaussian_draw(key, mean, cov):
    """Draw from N(mean, cov); the semi-definite square root tolerates covariances that are
    rank-deficient up to roundoff (backward-sampling covariances often are)."""
    eps = jax.random.normal(key, mean.shape, dtype=mean.dtype)
    return mean + psd_sqrt(symmetrise(cov)) @ eps


def log_likelihood_complete(A, Q, H, R, m0, P0, y, tol: float = 1e-13) -> Float[Array, ""]:
    r"""Exact log-likelihood for a fully observed record, with the covariance recursion cut short.

    For a time-invariant model the covariance recursion does not depend on
    the data and converges geometrically to the steady state of the Riccati
    equation. We iterate it (a ``while_loop``) only until every entry of the
    predicted covariance stops changing to relative precision ``tol``
    (relative to :math:`\sqrt{P_{ii} P_{jj}}`), keeping the gains; from then on
    the gains are frozen and only the mean is propagated, a scan of a few
    vector operations per step. With ``tol`` at rounding level this is the
    same number as :func:`log_likelihood` to floating-point precision (it is
    tested to agree to ~1e-10 relative), for a fraction of the cost on long
    records. If the recursion has not converged by the end, it simply ran in
    full. Missing samples break time invariance: use :func:`log_likelihood`.
    """
    T, d = y.shape

    # Phase 1: the full filter through the transient, until the predicted
    # covariance has converged. The carry is small, so this vmaps cheaply.
    def cond(carry):
        t, _, _, _, done = carry
        return (t < T) & ~done

    def body(carry):
        t, m, P, ll, _ = carry
        y_t = jax.lax.dynamic_index_in_dim(y, t, keepdims=False)
        m_f, P_f, ll_t = _update(m, P, H, R, y_t, jnp.ones(d, bool))
        P_next = symmetrise(A @ P_f @ A.T + Q)
        scale = jnp.sqrt(jnp.outer(jnp.abs(jnp.diagonal(P)), jnp.abs(jnp.diagonal(P))))
        done = jnp.all(jnp.abs(P_next - P) <= tol * scale)
        return t + 1, A @ m_f, P_next, ll + ll_t, done

    init = (jnp.zeros((), jnp.int32), m0, P0, jnp.zeros((), m0.dtype), jnp.zeros((), bool))
    t_conv, m, P, ll, _ = jax.lax.while_loop(cond, body, init)

    # Phase 2: gains frozen at the converged covariance; only the mean moves.
    r = jnp.diagonal(R)
    ks, ss = [], []
    for i in range(d):
        h = H[i]
        Ph = P @ h
        s_i = h @ Ph + r[i]
        k = Ph / s_i
        P = symmetrise(P - s_i * jnp.outer(k, k))
        ks.append(k)
        ss.append(s_i)

    def _step(carry, inputs):
        m, ll = carry
        t, y_t = inputs
        active = t >= t_conv
        ll_t = jnp.zeros((), dtype=m.dtype)
        m_new = m
        for i in range(d):
            v = y_t[i] - H[i] @ m_new
            m_new = m_new + ks[i] * v
            ll_t = ll_t - 0.5 * (v * v / ss[i] + jnp.log(ss[i]) + _LOG_2PI)
        m = jnp.where(active, A @ m_new, m)
        return (m, ll + jnp.where(active, ll_t, 0.0)), None

    (_, ll), _ = jax.lax.scan(_step, (m, ll), (jnp.arange(T), y))
    return ll
