r"""The particle sampler's latent path :math:`g = (x_f, w)` (force states and the mechanical
states' within-step noise, :mod:`latentforce.inference.particle_model`): its Gaussian density, whitening and
colouring, and the observation density of a state path."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from latentforce.inference import particle_model
from latentforce.linalg import cho_solve, cholesky, solve_lower, symmetrise

_LOG_2PI = math.log(2.0 * math.pi)


def latent_log_density(tr: particle_model.Transition, g: Float[Array, "T nl"]) -> Float[Array, ""]:
    """:func:`gp_path_log_density` given the transition at :math:`\theta`."""
    T, nl = g.shape
    cP, cQ = particle_model._chol(tr.Pinf), particle_model._chol(tr.Q)
    eps = _whiten(tr, g, cP, cQ)
    logdetQ = 2.0 * jnp.sum(jnp.log(jnp.diag(cQ)))
    logdetP = 2.0 * jnp.sum(jnp.log(jnp.diag(cP)))
    return -0.5 * jnp.sum(eps**2) - 0.5 * ((T - 1) * logdetQ + logdetP) - 0.5 * T * nl * _LOG_2PI


def whiten(tr: particle_model.Transition, g: Float[Array, "T nl"]) -> Float[Array, "T nl"]:
    r"""Innovations :math:`\varepsilon_1 = L_\infty^{-1} g_1`, :math:`\varepsilon_t = L_Q^{-1}(g_t - A g_{t-1})`."""
    return _whiten(tr, g, particle_model._chol(tr.Pinf), particle_model._chol(tr.Q))


def _whiten(tr: particle_model.Transition, g, cP, cQ):
    # one small triangular inverse applied as a matrix product: XLA's CPU triangular
    # solve with T right-hand sides cost ~1 ms at T = 1024, the product ~10 us
    e1 = solve_lower(cP, g[0])
    cQ_inv = solve_lower(cQ, jnp.eye(cQ.shape[0]))
    resid = g[1:] - g[:-1] @ tr.A.T
    return jnp.concatenate([e1[None], resid @ cQ_inv.T])


def colour(tr: particle_model.Transition, eps: Float[Array, "T nl"]) -> Float[Array, "T nl"]:
    """The latent path with innovations ``eps`` (inverse of :func:`whiten`)."""
    g1 = particle_model._chol(tr.Pinf) @ eps[0]
    noise = eps[1:] @ particle_model._chol(tr.Q).T

    def _step(g, q):
        nxt = tr.A @ g + q
        return nxt, nxt

    _, gs = jax.lax.scan(_step, g1, noise)
    return jnp.concatenate([g1[None], gs])


class ObservationDensity(NamedTuple):
    """Per-time masked Gaussian observation terms (independent of :math:`\\theta`)."""

    y: Float[Array, "T d"]  # zero where missing
    maskf: Float[Array, "T d"]
    Rinv: Float[Array, "T d d"]  # zero rows/columns where missing
    const: Float[Array, " T"]
    R: Float[Array, "d d"]  # the channels' noise covariance (the Gaussian moves build their proposals from it)


def observation_density(pm: particle_model.ParticleModel, y, mask, R=None) -> ObservationDensity:
    """Precompute :math:`R_t^{-1}` and normalising constants of the observed channels (``R``
    default ``pm.R``)."""
    R = pm.R if R is None else R
    maskf = jnp.asarray(mask, dtype=float)
    yz = jnp.where(jnp.asarray(mask, dtype=bool), jnp.nan_to_num(jnp.asarray(y, dtype=float)), 0.0)

    def _one(m):
        # unit variance on the missing channels keeps R_t invertible; they are masked out below
        R_t = R * jnp.outer(m, m) + jnp.diag(1.0 - m)
        c = cholesky(symmetrise(R_t))
        inv = cho_solve(c, jnp.eye(R_t.shape[0])) * jnp.outer(m, m)
        return symmetrise(inv), -jnp.sum(jnp.log(jnp.diag(c))) - 0.5 * jnp.sum(m) * _LOG_2PI

    Rinv, const = jax.vmap(_one)(maskf)
    return ObservationDensity(yz, maskf, Rinv, const, jnp.asarray(R, dtype=float))


def predicted_observations(pm: particle_model.ParticleModel, path: Float[Array, "T n"]) -> Float[Array, "T d"]:
    r"""Noise-free observations :math:`c(\mathrm{mech}_t) + D x_{f,t}` of a path."""
    return jax.vmap(pm.offset)(path[:, pm.layout.mech]) + path[:, pm.layout.force_states] @ pm.D.T


def observation_residuals(
    pm: particle_model.ParticleModel, od: ObservationDensity, path: Float[Array, "T n"]
) -> Float[Array, "T d"]:
    r""":math:`y_t - c(\mathrm{mech}_t) - D x_{f,t}` on the observed channels, zero on the missing ones."""
    return (od.y - predicted_observations(pm, path)) * od.maskf


def observation_log_likelihood(
    pm: particle_model.ParticleModel, od: ObservationDensity, path: Float[Array, "T n"]
) -> Float[Array, ""]:
    r""":math:`\sum_t \log N(y_t; c(\mathrm{mech}_t) + D x_{f,t}, R)` over the observed channels."""
    r = observation_residuals(pm, od, path)
    return jnp.sum(od.const) - 0.5 * jnp.einsum("ti,tij,tj->", r, od.Rinv, r)


def gp_prior_path(key: Array, tr: particle_model.Transition, T: int) -> Float[Array, "T nl"]:
    """One draw of the latent path from its prior."""
    return colour(tr, jax.random.normal(key, (T, tr.A.shape[0])))
