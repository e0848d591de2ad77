r"""Parallel-in-time Kalman filter and RTS smoother (associative scans).

The same model, conventions and results as :mod:`latentforce.inference.kalman`
(column states, ``m0, P0`` the prior of the *first sampled* state, per-channel
``mask``), computed with ``jax.lax.associative_scan`` in :math:`O(\log T)`
sequential depth instead of a :math:`T`-step ``lax.scan``: Särkkä &
García-Fernández (2021), "Temporal parallelization of Bayesian smoothers",
IEEE TAC 66(1), §IV (filter, Lemmas 7-8) and §V (smoother, Lemmas 9-10).
It does :math:`O(n^3)` more work per step than the sequential recursion, so it
pays only where the hardware runs many steps at once (a GPU) on long records;
:mod:`latentforce.inference.kalman_choice` decides which one runs.

Filtering elements. Each step :math:`k` is the affine-Gaussian map
:math:`p(x_k | x_{k-1}, y_k) = N(A_k x_{k-1} + b_k, C_k)` together with the
information form of the likelihood :math:`p(y_k | x_{k-1}) \propto
N_I(x_{k-1}; \eta_k, J_k)`. With :math:`S_k = H_k Q H_k^T + R`,
:math:`K_k = Q H_k^T S_k^{-1}` (Lemma 7):

.. math::
    A_k = (I - K_k H_k) F,\quad b_k = K_k y_k,\quad C_k = (I - K_k H_k) Q,\quad
    \eta_k = F^T H_k^T S_k^{-1} y_k,\quad J_k = F^T H_k^T S_k^{-1} H_k F,

and the first element is the update of the prior itself
(:math:`A_1 = 0, b_1 = m_1, C_1 = P_1, \eta_1 = 0, J_1 = 0`). Missing
channels: ``H_k`` is ``H`` with the rows of the unobserved channels zeroed
and ``y_k`` zeroed there, so they contribute nothing (their gain column,
:math:`\eta` and :math:`J` terms vanish); a step with nothing observed is a
pure prediction :math:`(F, 0, Q, 0, 0)`. The prefix products (Lemma 8,
``_filtering_operator``) are the filtered moments :math:`b, C`.

Log-likelihood. With the filtered moments in hand, every one-step prediction
:math:`N(m^-_t, P^-_t)` is known, and :math:`\log p(y_t | y_{1:t-1})` is
computed for all :math:`t` at once by the sequential filter's own scalar
update (vmapped over time), so both give the same number by the same
arithmetic given the same predictions.

Smoothing elements (Lemma 9): for :math:`k < T`,
:math:`E_k = P_k F^T (P^-_{k+1})^{-1}`, :math:`g_k = m_k - E_k m^-_{k+1}`,
:math:`L_k = P_k - E_k P^-_{k+1} E_k^T`; :math:`(E_T, g_T, L_T) = (0, m_T,
P_T)`; combined from the end (Lemma 10, ``_smoothing_operator``).

Backward sampling: :math:`x_t = E_t x_{t+1} + g_t + w_t`, :math:`w_t \sim
N(0, L_t)`, is a chain of affine maps, composed by the same scan without
the covariance (:func:`parallel_sample_smoothed_trajectory`).

Numerics: float64; every covariance-like block symmetrised after each
combination; the non-symmetric :math:`I + C_i J_j` of Lemma 8 is solved
(Gauss-Jordan with pivoting, :func:`latentforce.linalg.solve`), never
inverted; :math:`S_k` by Cholesky. Like the rest of the package, no LAPACK
call is compiled in (see :mod:`latentforce.linalg`), and everything is
differentiable in forward and reverse mode.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from latentforce.inference.kalman import (
    FilterResult,
    SmootherResult,
    _gaussian_draw,
    _update,
)
from latentforce.linalg import cho_solve, cholesky, solve, solve_lower, symmetrise


class FilteringElements(NamedTuple):
    r"""Elements of the parallel filter, Lemma 7 (leading axis: time)."""

    A: Float[Array, "T n n"]
    b: Float[Array, "T n"]
    C: Float[Array, "T n n"]
    eta: Float[Array, "T n"]
    J: Float[Array, "T n n"]


class SmoothingElements(NamedTuple):
    r"""Elements of the parallel smoother, Lemma 9 (leading axis: time)."""

    E: Float[Array, "T n n"]
    g: Float[Array, "T n"]
    L: Float[Array, "T n n"]


def _step_element(A, Q, H, r, y_t, mask_t):
    """Element k >= 2 of Lemma 7, with the unobserved channels' rows of ``H`` and ``y`` zeroed."""
    Hm = jnp.where(mask_t[:, None], H, 0.0)
    y_t = jnp.where(mask_t, y_t, 0.0)
    # An unobserved channel's row and column of S are zero but for the diagonal: put 1 there
    # (any positive number does: its gain column, eta and J terms are zero whatever it is).
    S = symmetrise(Hm @ Q @ Hm.T + jnp.diag(jnp.where(mask_t, r, 1.0)))
    chol = cholesky(S)
    HF = Hm @ A
    K = cho_solve(chol, Hm @ Q).T  # Q H^T S^{-1}, (n, d)
    A_k = A - K @ HF
    b_k = K @ y_t
    C_k = symmetrise(Q - K @ S @ K.T)
    W = solve_lower(chol, HF)  # chol^{-1} H F: J = W^T W is symmetric by construction
    eta_k = W.T @ solve_lower(chol, y_t)
    J_k = W.T @ W
    return FilteringElements(A_k, b_k, C_k, eta_k, J_k)


def filtering_elements(
    A: Float[Array, "n n"],
    Q: Float[Array, "n n"],
    H: Float[Array, "d n"],
    R: Float[Array, "d d"],
    m0: Float[Array, " n"],
    P0: Float[Array, "n n"],
    y: Float[Array, "T d"],
    mask: Bool[Array, "T d"],
) -> FilteringElements:
    """The ``T`` filtering elements of Lemma 7 (module docstring); ``y`` zero where masked."""
    n = A.shape[0]
    r = jnp.diagonal(R)
    rest = jax.vmap(_step_element, in_axes=(None, None, None, None, 0, 0))(A, Q, H, r, y[1:], mask[1:])
    m1, P1, _ = _update(m0, P0, H, R, y[0], mask[0])
    zeros = jnp.zeros((1, n, n), dtype=A.dtype)
    first = FilteringElements(zeros, m1[None], P1[None], jnp.zeros((1, n), A.dtype), zeros)
    return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b], axis=0), first, rest)


def _filtering_operator(earlier: FilteringElements, later: FilteringElements) -> FilteringElements:
    r"""Lemma 8: the element of steps ``i`` then ``j`` from those of ``i`` (earlier) and ``j`` (later).

    .. math::
        M = I + C_i J_j, \quad
        A_{ij} = A_j M^{-1} A_i, \quad b_{ij} = A_j M^{-1}(b_i + C_i \eta_j) + b_j, \quad
        C_{ij} = A_j M^{-1} C_i A_j^T + C_j, \\
        \eta_{ij} = A_i^T M^{-T} (\eta_j - J_j b_i) + \eta_i, \quad
        J_{ij} = A_i^T M^{-T} J_j A_i + J_i,

    using :math:`(I + J_j C_i) = M^T` (both :math:`C` and :math:`J` symmetric).
    """
    Ai, bi, Ci, etai, Ji = earlier
    Aj, bj, Cj, etaj, Jj = later
    n = Ai.shape[-1]
    M = jnp.eye(n, dtype=Ai.dtype) + Ci @ Jj
    X = solve(M, jnp.concatenate([Ai, (bi + Ci @ etaj)[:, None], Ci], axis=1))
    XA, Xb, XC = X[:, :n], X[:, n], X[:, n + 1 :]
    Y = solve(M.T, jnp.concatenate([(etaj - Jj @ bi)[:, None], Jj @ Ai], axis=1))
    Yeta, YJ = Y[:, 0], Y[:, 1:]
    return FilteringElements(
        Aj @ XA,
        Aj @ Xb + bj,
        symmetrise(Aj @ symmetrise(XC) @ Aj.T + Cj),
        Ai.T @ Yeta + etai,
        symmetrise(Ai.T @ YJ + Ji),
    )


def parallel_kalman_filter(
    A: Float[Array, "n n"],
    Q: Float[Array, "n n"],
    H: Float[Array, "d n"],
    R: Float[Array, "d d"],
    m0: Float[Array, " n"],
    P0: Float[Array, "n n"],
    y: Float[Array, "T d"],
    mask: Bool[Array, "T d"] | None = None,
) -> FilterResult:
    """The Kalman filter by an associative scan: same arguments and result as
    :func:`latentforce.inference.kalman.kalman_filter`."""
    if mask is None:
        mask = jnp.isfinite(y)
    y = jnp.where(mask, y, 0.0)
    elements = filtering_elements(A, Q, H, R, m0, P0, y, mask)
    scanned = jax.lax.associative_scan(jax.vmap(_filtering_operator), elements)
    means = scanned.b
    covs = jax.vmap(symmetrise)(scanned.C)
    pred_means = means @ A.T
    pred_covs = jax.vmap(lambda P: symmetrise(A @ P @ A.T + Q))(covs)
    # log p(y_t | y_{1:t-1}) from the prediction into step t: the prior at t = 1, else the
    # filter's prediction from t - 1; the sequential filter's scalar update, vmapped over t.
    prior_means = jnp.concatenate([m0[None], pred_means[:-1]], axis=0)
    prior_covs = jnp.concatenate([P0[None], pred_covs[:-1]], axis=0)
    _, _, ll_t = jax.vmap(_update, in_axes=(0, 0, None, None, 0, 0))(prior_means, prior_covs, H, R, y, mask)
    return FilterResult(means, covs, pred_means, pred_covs, jnp.sum(ll_t))


def parallel_log_likelihood(A, Q, H, R, m0, P0, y, mask=None) -> Float[Array, ""]:
    """Exact log-likelihood ``log p(y_{1:T})`` from :func:`parallel_kalman_filter`."""
    return parallel_kalman_filter(A, Q, H, R, m0, P0, y, mask).log_likelihood


def smoothing_elements(A: Float[Array, "n n"], filtered: FilterResult) -> SmoothingElements:
    """The ``T`` smoothing elements of Lemma 9 (module docstring)."""

    def element(m_f, P_f, m_p, P_p):
        # the RTS gain P_f A^T (P^-)^{-1} by a solve against the predicted covariance,
        # as in latentforce.inference.kalman.rts_smoother
        E = solve(P_p, A @ P_f).T
        return E, m_f - E @ m_p, symmetrise(P_f - E @ P_p @ E.T)

    E, g, L = jax.vmap(element)(
        filtered.means[:-1], filtered.covs[:-1], filtered.pred_means[:-1], filtered.pred_covs[:-1]
    )
    n = A.shape[0]
    E = jnp.concatenate([E, jnp.zeros((1, n, n), A.dtype)], axis=0)
    g = jnp.concatenate([g, filtered.means[-1:]], axis=0)
    L = jnp.concatenate([L, filtered.covs[-1:]], axis=0)
    return SmoothingElements(E, g, L)


def _smoothing_operator(later: SmoothingElements, earlier: SmoothingElements) -> SmoothingElements:
    r"""Lemma 10 for a scan from the end: :math:`E = E_k E_l,\ g = E_k g_l + g_k,\
    L = E_k L_l E_k^T + L_k` with ``k`` the earlier step and ``l`` the later
    (``lax.associative_scan(..., reverse=True)`` passes the later one first)."""
    El, gl, Ll = later
    Ek, gk, Lk = earlier
    return SmoothingElements(Ek @ El, Ek @ gl + gk, symmetrise(Ek @ Ll @ Ek.T + Lk))


def parallel_rts_smoother(A: Float[Array, "n n"], filtered: FilterResult) -> SmootherResult:
    """The RTS smoother by an associative scan from the end: same arguments and result as
    :func:`latentforce.inference.kalman.rts_smoother` (``filtered`` from either filter)."""
    elements = smoothing_elements(A, filtered)
    scanned = jax.lax.associative_scan(jax.vmap(_smoothing_operator), elements, reverse=True)
    return SmootherResult(scanned.g, jax.vmap(symmetrise)(scanned.L), filtered.log_likelihood)


def parallel_kalman_smoother(A, Q, H, R, m0, P0, y, mask=None) -> SmootherResult:
    """Parallel filter then parallel smoother; as :func:`latentforce.inference.kalman.kalman_smoother`."""
    return parallel_rts_smoother(A, parallel_kalman_filter(A, Q, H, R, m0, P0, y, mask))


def parallel_sample_smoothed_trajectory(
    key, A: Float[Array, "n n"], Q: Float[Array, "n n"], filtered: FilterResult
) -> Float[Array, "T n"]:
    r"""One draw of :math:`x_{1:T} \sim p(x_{1:T} | y_{1:T})`, by an associative scan.

    The draw of :func:`latentforce.inference.kalman.sample_smoothed_trajectory`
    (same key, same per-step normal draws, same square roots), with the
    backward recursion :math:`x_t = E_t x_{t+1} + h_t`,
    :math:`h_t = g_t + L_t^{1/2} \varepsilon_t` (Lemma 9's elements) composed
    as affine maps from the end. ``Q`` is unused (the predictions are in
    ``filtered``); it is kept for the sequential function's signature.
    """
    T = filtered.means.shape[0]
    keys = jax.random.split(key, T)
    el = smoothing_elements(A, filtered)
    # h_t = g_t + sqrt(L_t) eps_t: a draw from N(g_t, L_t), as the sequential sampler draws it
    h = jax.vmap(_gaussian_draw)(keys, el.g, el.L)

    def compose(later, earlier):
        (El, hl), (Ek, hk) = later, earlier
        return Ek @ El, Ek @ hl + hk

    _, xs = jax.lax.associative_scan(jax.vmap(compose), (el.E, h), reverse=True)
    return xs
