r"""Exact inference for linear latent force models: ``kalman`` and ``kalman-mcmc``.

``kalman``: every parameter known; the Kalman filter and RTS smoother give
the exact posterior of the states and force, and the exact log-likelihood.

``kalman-mcmc`` (Algorithm 1, ISMA 2018): random-walk Metropolis over any
subset of the physical and GP parameters, in the softplus space of Eq. (27),
with the Kalman filter's exact log-likelihood (the energy function, Eq.
24-26) plus the log prior and the log-Jacobian of the transform. Chains are
vmapped and the iterations scanned: one compiled program.

Trajectories: the paper plots the smoother at one point estimate (the CDF
median), which ignores the parameter uncertainty. We also report the honest
posterior of each state, mixed over a few hundred posterior draws
:math:`\theta_j`: by the law of total variance,

.. math:: E[x_t] = \overline{m_t(\theta_j)}, \qquad
          \operatorname{Var}[x_t] = \overline{P_t(\theta_j)} + \operatorname{Var}_j[m_t(\theta_j)],

and one backward-sampled trajectory per draw for ``posterior.nc``.
"""

from __future__ import annotations

import functools
import math
import time as _time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.compile import jit
from latentforce.inference import mcmc
from latentforce.inference.kalman import (
    kalman_filter,
    log_likelihood,
    log_likelihood_complete,
    rts_smoother,
    sample_smoothed_trajectory,
)
from latentforce.models import LatentForceModel
from latentforce.priors import Prior, log_prob_unconstrained, softplus, softplus_inverse


class Initial(NamedTuple):
    """A user-given prior of the first state: mean and standard deviation per state."""

    mean: np.ndarray
    sd: np.ndarray


def initial_moments(model: LatentForceModel, params: dict, initial: Initial | None):
    """``(m0, P0)``: the user's ``[initial]`` section, else the model's default."""
    if initial is None:
        return model.default_initial(params)
    return jnp.asarray(initial.mean, dtype=float), jnp.diag(jnp.asarray(initial.sd, dtype=float) ** 2)


def linear_gaussian(model: LatentForceModel, params: dict, dt: float, initial: Initial | None = None):
    """The discrete linear-Gaussian model ``(A, Q, H, R, m0, P0)`` for ``params``."""
    A, Q = model.discretise(params, dt)
    H, R = model.observation(params)
    m0, P0 = initial_moments(model, params, initial)
    return A, Q, H, R, m0, P0


def smooth(model: LatentForceModel, params: dict, y, mask, dt: float, initial: Initial | None = None):
    """Exact smoothed moments and log-likelihood at fixed ``params`` (method ``kalman``)."""
    A, Q, H, R, m0, P0 = linear_gaussian(model, params, dt, initial)
    filt = kalman_filter(A, Q, H, R, m0, P0, jnp.asarray(y), jnp.asarray(mask))
    return rts_smoother(A, filt)


def state_moments(model: LatentForceModel, means, covs):
    """Split smoothed moments into displacement / velocity / force (mean, sd) arrays."""
    var = jnp.diagonal(covs, axis1=-2, axis2=-1)
    out = {}
    for name, idx in (("displacement", model.displacement_index()), ("velocity", model.velocity_index()),
                      ("force", model.force_index())):
        out[name] = (means[..., idx], jnp.sqrt(jnp.clip(var[..., idx], 0.0)))
    return out


class MCMCOutput(NamedTuple):
    """Raw output of :func:`run_kalman_mcmc` (numpy arrays)."""

    names: tuple[str, ...]
    draws: dict                   # name -> (chains, iterations) physical values
    accepted: np.ndarray          # (chains, iterations)
    log_likelihood: np.ndarray    # (chains, iterations)
    acceptance: np.ndarray        # (chains,) post-burn-in acceptance rate
    proposal_scale: np.ndarray    # (chains,) adapted global scale
    wall_time_s: float


def make_log_posterior(model: LatentForceModel, fixed: dict, names: tuple[str, ...], priors: tuple[Prior, ...],
                       y, mask, dt: float, initial: Initial | None = None) -> tuple[Callable, Callable]:
    """Log posterior of the unconstrained parameter vector, and its log-likelihood part."""
    complete = bool(np.all(mask))
    y = jnp.asarray(np.where(mask, y, 0.0))
    mask = jnp.asarray(mask)

    def params_of(x):
        params = dict(fixed)
        for i, name in enumerate(names):
            params[name] = softplus(x[i])
        return params

    def loglik(x):
        lg = linear_gaussian(model, params_of(x), dt, initial)
        # A complete record is time invariant: the exact steady-state shortcut applies.
        return log_likelihood_complete(*lg, y) if complete else log_likelihood(*lg, y, mask)

    def logpost(x):
        lp = sum(log_prob_unconstrained(prior, x[i]) for i, prior in enumerate(priors))
        # Evaluate the filter only where the prior allows (an impossible prior value is -inf anyway).
        return lp + loglik(x)

    return logpost, loglik


def run_kalman_mcmc(key, model: LatentForceModel, fixed: dict, free: dict, y, mask, dt: float, *,
                    iterations: int, burn_in: int, chains: int, initial: Initial | None = None,
                    progress: Callable | None = None, chunk: int = 1000) -> MCMCOutput:
    """Random-walk Metropolis over the ``free`` parameters (Algorithm 1, ISMA 2018).

    ``free`` maps a parameter name to ``(prior, init)``; ``fixed`` holds the
    known values. Chains start dispersed around ``init`` (a factor
    ``exp(0.3 z)``, ``z ~ N(0, 1)``), never at the truth. ``progress(done,
    total, acceptance)`` is called between chunks of ``chunk`` iterations.
    """
    t0 = _time.perf_counter()
    names = tuple(free)
    priors = tuple(free[n][0] for n in names)
    inits = np.array([float(free[n][1]) for n in names])
    logpost, loglik = make_log_posterior(model, fixed, names, priors, y, mask, dt, initial)
    p = len(names)
    target = mcmc.target_acceptance(p)

    key_init, key_run = jax.random.split(key)
    z = np.asarray(jax.random.normal(key_init, (chains, p)))
    theta0 = inits[None, :] * np.exp(0.3 * z) if chains > 1 else inits[None, :]
    x0 = np.asarray(softplus_inverse(jnp.asarray(theta0)))
    # A 10 % step in the physical value (or 0.1 in x where the value is below one).
    sd0 = 0.1 * np.maximum(1.0, theta0)

    init_fn = jit(jax.vmap(lambda x, s: mcmc.init(x, logpost, s)))
    states = init_fn(jnp.asarray(x0), jnp.asarray(sd0))
    shape_at = tuple(sorted({burn_in // 4, burn_in // 2, (3 * burn_in) // 4} - {0}))

    n_chunk = _chunk_size(burn_in, iterations, chunk)
    # Whole chunks: the burn-in may be rounded up (never down); extra draws are dropped.
    burn_total = -(-burn_in // n_chunk) * n_chunk
    total = burn_total + -(-iterations // n_chunk) * n_chunk

    @jit
    @functools.partial(jax.vmap, in_axes=(0, 0, None, None))
    def runner(k, s, start, adapt):
        return mcmc.run_chain(k, s, logpost, n_chunk, adapt=adapt, adapt_shape_at=shape_at,
                              target=target, start=start)

    done = 0
    xs_all, acc_all, ld_all = [], [], []
    run_keys = jax.random.split(key_run, chains)
    while done < total:
        adapt = done < burn_total
        keys = jax.vmap(lambda k: jax.random.fold_in(k, done))(run_keys)
        states, xs, infos = runner(keys, states, done, adapt)
        if not adapt:
            xs_all.append(np.asarray(xs))
            acc_all.append(np.asarray(infos.accepted))
            ld_all.append(np.asarray(infos.logdensity))
        done += n_chunk
        if progress is not None:
            progress(done, total, float(np.mean(np.asarray(infos.accepted))))

    xs = np.concatenate(xs_all, axis=1)[:, :iterations]
    accepted = np.concatenate(acc_all, axis=1)[:, :iterations]
    lp = np.concatenate(ld_all, axis=1)[:, :iterations]
    # The log-likelihood part of each draw: log posterior minus log prior (cheap, exact).
    log_prior = sum(np.asarray(log_prob_unconstrained(prior, jnp.asarray(xs[..., i])))
                    for i, prior in enumerate(priors))
    draws = {n: np.asarray(softplus(jnp.asarray(xs[..., i]))) for i, n in enumerate(names)}
    return MCMCOutput(names, draws, accepted, lp - log_prior, accepted.mean(axis=1),
                      np.exp(np.asarray(states.log_scale)), _time.perf_counter() - t0)


def _chunk_size(burn_in: int, iterations: int, limit: int) -> int:
    """The largest chunk <= ``limit`` that divides both phases, so one compiled
    program runs every chunk; if they share no divisor of useful size, a plain
    ``limit``-sized chunk (the caller rounds the phases up to whole chunks)."""
    g = math.gcd(burn_in, iterations) if burn_in else iterations
    best = max((d for d in range(1, min(limit, g) + 1) if g % d == 0), default=1)
    return best if best >= min(100, limit) else min(limit, max(burn_in, iterations))


def mixture_posterior(key, model: LatentForceModel, fixed: dict, draws: dict, y, mask, dt: float, *,
                      n_mix: int = 200, initial: Initial | None = None, batch: int = 25,
                      point: dict | None = None):
    """Posterior state moments mixed over ``n_mix`` parameter draws, and sampled paths.

    Returns ``(moments, paths, point_result)``: ``moments[name] = (mean, sd)``
    with shapes ``(T, width)``; ``paths[name]`` with shape
    ``(chains, d, T, width)`` where ``d = n_mix // chains`` evenly thinned
    draws per chain, one backward-sampled trajectory per parameter draw;
    ``point_result`` is ``(moments, log_likelihood)`` of the smoother at the
    parameter values ``point`` (e.g. the CDF median), or ``None``. One compiled batch program
    does all of it (the last batch is padded).
    """
    names = tuple(draws)
    chains, n_iter = next(iter(draws.values())).shape
    per_chain = max(1, n_mix // chains)
    idx = np.linspace(0, n_iter - 1, per_chain).round().astype(int)
    thetas = np.stack([draws[n][:, idx] for n in names], axis=-1)  # (chains, d, p)
    flat = thetas.reshape(-1, len(names))
    count = flat.shape[0]
    if point is not None:
        flat = np.concatenate([flat, np.array([[point[n] for n in names]])])
    batch = min(batch, flat.shape[0])
    n_pad = -flat.shape[0] % batch
    flat = np.concatenate([flat, np.repeat(flat[-1:], n_pad, axis=0)])
    y, mask = jnp.asarray(y), jnp.asarray(mask)

    def one(k, theta):
        params = dict(fixed)
        for i, n in enumerate(names):
            params[n] = theta[i]
        A, Q, H, R, m0, P0 = linear_gaussian(model, params, dt, initial)
        filt = kalman_filter(A, Q, H, R, m0, P0, y, mask)
        sm = rts_smoother(A, filt)
        path = sample_smoothed_trajectory(k, A, Q, filt)
        return sm.means, jnp.diagonal(sm.covs, axis1=-2, axis2=-1), path, filt.log_likelihood

    batched = jit(jax.vmap(one))
    keys = jax.random.split(key, flat.shape[0])
    parts = [batched(keys[start:start + batch], jnp.asarray(flat[start:start + batch]))
             for start in range(0, flat.shape[0], batch)]
    m_all, v_all, p_all, ll_all = (np.concatenate([np.asarray(part[i]) for part in parts]) for i in range(4))
    mean = m_all[:count].mean(0)
    var = v_all[:count].mean(0) + m_all[:count].var(0)
    paths = p_all[:count].reshape(chains, per_chain, *p_all.shape[1:])
    index = (("displacement", model.displacement_index()), ("velocity", model.velocity_index()),
             ("force", model.force_index()))
    moments = {name: (mean[:, ix], np.sqrt(var[:, ix])) for name, ix in index}
    sampled = {name: paths[..., ix] for name, ix in index}
    point_result = None
    if point is not None:
        point_result = ({name: (m_all[count][:, ix], np.sqrt(v_all[count][:, ix])) for name, ix in index},
                        float(ll_all[count]))
    return moments, sampled, point_result
