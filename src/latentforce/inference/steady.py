r"""The RTS smoother of a long, fully observed record, with its covariances in steady state.

For a time-invariant model observed at every step the covariance recursions
do not depend on the data. The filter's predicted covariance converges
geometrically to the Riccati equation's fixed point, and, read backwards
from the end of the record, so does the smoother's. Away from both ends of
a long record every covariance and gain is therefore constant:

.. math::
    P^f_t = P^f_\infty,\; G_t = G_\infty \;(t \ge K-1), \qquad
    P^s_t = P^s_\infty \;(K \le t \le T-1-K),

and only the means need a pass over all ``T`` samples (a few vector
operations per step). Here the covariance recursions run over the first
``K`` steps (forward, the filter's transient), the last ``K`` (backward
from :math:`P^f_\infty`, the smoother's transient) and the first ``K`` again
(backward, time-varying): memory :math:`O(Tn + Kn^2)` instead of
:math:`O(Tn^2)`, and the same numbers as the full smoother to rounding
whenever both transients have died out within ``K`` steps, which
``converged`` reports (the caller falls back to the full smoother where
not). Same model and conventions as :mod:`latentforce.inference.kalman`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from latentforce.inference.kalman import _LOG_2PI
from latentforce.linalg import psd_sqrt, solve, symmetrise

#: transient steps kept with full covariances at each end of the record, at most
TRANSIENT = 2048
#: ... and at least
MIN_TRANSIENT = 128
#: relative change (to sqrt(P_ii P_jj)) under which a covariance counts as converged. 1e-12 sat
#: at the rounding floor of the backward recursion (P_f + G (P_s - P_p) G^T cancels): on the 3-DOF
#: frame a longer transient was flagged *less* often converged than a shorter one.
TOL = 1e-10


class SteadySmoother(NamedTuple):
    means: Float[Array, "T n"]
    variances: Float[Array, "T n"]  # diagonals of the smoothed covariances
    log_likelihood: Float[Array, ""]
    path: Float[Array, "T n"]  # a backward-sampled trajectory (zeros unless asked for)
    converged: Bool[Array, ""]  # both transients died out within K steps


def applies(T: int, complete: bool, K: int | None = None) -> bool:
    """Whether the steady-state smoother serves a record: fully observed and longer than 2K+1."""
    return complete and T >= 2 * (TRANSIENT if K is None else K) + 2


def settling_steps(A, Q, H, R, P0, max_steps: int) -> Array:
    """Steps the filter's predicted covariance takes to converge from ``P0`` (to :data:`TOL`),
    at most ``max_steps``: what the transient ``K`` must cover (data-free, so one per model)."""
    r = jnp.diagonal(R)

    def cond(carry):
        t, _, done = carry
        return (t < max_steps) & ~done

    def body(carry):
        t, P_p, _ = carry
        P_next = symmetrise(A @ _scalar_updates(P_p, H, r)[2] @ A.T + Q)
        return t + 1, P_next, _close(P_next, P_p)

    t, _, _ = jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), P0, jnp.zeros((), bool)))
    return t


def transient_for(steps: int, T: int) -> int | None:
    """The transient ``K`` (a power of two, with a margin over ``steps`` settling steps, at least
    :data:`MIN_TRANSIENT`, at most :data:`TRANSIENT`) for a record of ``T`` samples; None where
    the record is too short for it (:func:`applies`)."""
    K = MIN_TRANSIENT
    while K < 1.25 * steps + 16 and K < TRANSIENT:
        K *= 2
    K = min(K, TRANSIENT)
    return K if applies(T, True, K) else None


def _scalar_updates(P, H, r):
    """Sequential scalar updates of ``P`` (one per channel): gains, innovation variances, P_f."""
    ks, ss = [], []
    for i in range(H.shape[0]):
        Ph = P @ H[i]
        s = H[i] @ Ph + r[i]
        k = Ph / s
        P = symmetrise(P - s * jnp.outer(k, k))
        ks.append(k)
        ss.append(s)
    return jnp.stack(ks), jnp.stack(ss), P


def _close(a, b, tol=TOL):
    d = jnp.sqrt(jnp.abs(jnp.outer(jnp.diagonal(a), jnp.diagonal(a))))
    return jnp.all(jnp.abs(a - b) <= tol * d)


def steady_smoother(
    A, Q, H, R, m0, P0, y: Float[Array, "T d"], key=None, K: int | None = None, rows=None
) -> SteadySmoother:
    r"""Smoothed means, variances and log-likelihood of a complete record (module doc).

    With ``key``, also one trajectory drawn from the smoothing distribution
    (forward filtering, backward sampling; Carter & Kohn 1994). With ``rows``
    (a ``(k, n)`` matrix :math:`G`), ``variances`` gains ``k`` columns:
    :math:`\operatorname{diag}(G P^s_t G^T)`, the variances of the linear
    combinations :math:`G x_t` (virtual sensors), cross-covariances included.
    """
    T, n = y.shape[0], m0.shape[0]
    K = TRANSIENT if K is None else K
    if T < 2 * K + 2:
        raise ValueError(f"steady_smoother needs T >= 2K + 2 = {2 * K + 2} samples, got {T}")
    r = jnp.diagonal(R)

    # Forward covariance transient: predicted P_p(t), gains and filtered P_f(t), t < K.
    def fwd(P_p, _):
        ks, ss, P_f = _scalar_updates(P_p, H, r)
        return symmetrise(A @ P_f @ A.T + Q), (P_p, ks, ss, P_f)

    P_next, (Pp, Ks, Ss, Pf) = jax.lax.scan(fwd, P0, None, length=K)
    forward_converged = _close(P_next, Pp[-1])
    Pf_inf, Pp_inf = Pf[-1], P_next

    # Means over the whole record: the first K steps with their own gains (scanned in),
    # then the frozen gains (constants of the loop body: no indexing per step).
    def mean_update(m_p, ll, y_t, k, s):
        m = m_p
        for i in range(H.shape[0]):
            v = y_t[i] - H[i] @ m
            m = m + k[i] * v
            ll = ll - 0.5 * (v * v / s[i] + jnp.log(s[i]) + _LOG_2PI)
        return m, ll

    def head_step(carry, inputs):
        m, ll = mean_update(*carry, *inputs)
        return (A @ m, ll), m

    def steady_step(carry, y_t):
        m, ll = mean_update(*carry, y_t, Ks[-1], Ss[-1])
        return (A @ m, ll), m

    carry, m_f_head = jax.lax.scan(head_step, (m0, jnp.zeros((), m0.dtype)), (y[:K], Ks, Ss))
    (_, ll), m_f_tail = jax.lax.scan(steady_step, carry, y[K:])
    m_f = jnp.concatenate([m_f_head, m_f_tail])
    m_p_next = m_f @ A.T  # m_p(t+1) = A m_f(t)

    # Smoother gains: G_t = P_f(t) A^T P_p(t+1)^{-1}; constant from t = K-1 on.
    Pp_shift = jnp.concatenate([Pp[1:], P_next[None]])  # P_p(t+1), t < K
    G_head = jax.vmap(lambda pf, pp: solve(pp, A @ pf).T)(Pf, Pp_shift)
    G_inf = solve(Pp_inf, A @ Pf_inf).T

    # Backward covariance transient at the end (steady P_f, G), then the head (time-varying).
    def back_tail(P_s, _):
        P = symmetrise(Pf_inf + G_inf @ (P_s - Pp_inf) @ G_inf.T)
        return P, P

    P_mid, tail = jax.lax.scan(back_tail, Pf_inf, None, length=K)
    backward_converged = _close(P_mid, tail[-2])

    def back_head(P_s, inputs):
        pf, pp, g = inputs
        P = symmetrise(pf + g @ (P_s - pp) @ g.T)
        return P, P

    _, head = jax.lax.scan(back_head, P_mid, (Pf, Pp_shift, G_head), reverse=True)
    if rows is None:
        diag = lambda P: jnp.diagonal(P, axis1=-2, axis2=-1)
    else:
        diag = lambda P: jnp.concatenate(
            [jnp.diagonal(P, axis1=-2, axis2=-1), jnp.einsum("ki,...ij,kj->...k", rows, P, rows)], axis=-1
        )
    # tail[j] is P_s at t = T-2-j; the last step P_s(T-1) = P_f(T-1) = P_f_inf.
    variances = jnp.concatenate(
        [
            diag(head),
            jnp.broadcast_to(diag(P_mid), (T - 2 * K - 1, diag(P_mid).shape[-1])),
            diag(tail[::-1]),
            diag(Pf_inf)[None],
        ]
    )

    def backward(x_last, G_step, late_inputs, head_inputs):
        """A backward recursion x_t = f(x_{t+1}): steady for t >= K-1, the head's own gains before."""
        x_mid, late = jax.lax.scan(lambda x, inp: (G_step(x, G_inf, *inp),) * 2, x_last, late_inputs, reverse=True)
        _, head = jax.lax.scan(lambda x, inp: (G_step(x, *inp),) * 2, x_mid, head_inputs, reverse=True)
        return jnp.concatenate([head, late, x_last[None]])

    # t = K-1 .. T-2 with G_inf; t = 0 .. K-2 with G_head[t].
    late = (m_f[K - 1 : T - 1], m_p_next[K - 1 : T - 1])
    head = (G_head[: K - 1], m_f[: K - 1], m_p_next[: K - 1])
    means = backward(m_f[-1], lambda x, G, mf, mp1: mf + G @ (x - mp1), late, head)

    path = jnp.zeros_like(means)
    if key is not None:
        # x_t | x_{t+1} ~ N(m_f + G (x_{t+1} - m_p(t+1)), P_f - G P_p(t+1) G^T).
        root_head = jax.vmap(lambda pf, pp, g: psd_sqrt(symmetrise(pf - g @ pp @ g.T)))(Pf, Pp_shift, G_head)
        root_inf = psd_sqrt(symmetrise(Pf_inf - G_inf @ Pp_inf @ G_inf.T))
        eps = jax.random.normal(key, (T, n), dtype=m0.dtype)
        x_last = m_f[-1] + psd_sqrt(Pf_inf) @ eps[-1]

        def draw(x, G, mf, mp1, e, root=root_inf):
            return mf + G @ (x - mp1) + root @ e

        path = backward(x_last, draw, late + (eps[K - 1 : T - 1],), head + (eps[: K - 1], root_head[: K - 1]))
    return SteadySmoother(means, variances, ll, path, forward_converged & backward_converged)
