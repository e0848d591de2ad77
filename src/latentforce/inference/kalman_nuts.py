r"""``kalman-nuts``: the No-U-Turn sampler (blackjax) on the exact Kalman log posterior.

The same target as ``kalman-mcmc`` (the Kalman filter's exact
log-likelihood, the priors and the softplus Jacobian, in the unconstrained
space of Eq. 27, ISMA 2018), explored by NUTS (Hoffman & Gelman 2014, as
implemented by blackjax) instead of a random walk.

Gradient: forward mode. The likelihood's steady-state shortcut and the
matrix exponential's squaring are ``while``/``fori`` loops, which reverse
mode cannot differentiate, so the log density is a ``jax.custom_vjp`` whose
forward pass computes the value and the full gradient by ``jax.jacfwd``
(``p`` tangents, one pass) and whose backward pass scales it: what blackjax
asks for through ``jax.value_and_grad``.

Tuning: the chains start over-dispersed around the posterior's modes
(:func:`latentforce.inference.kalman_mcmc.start_chains`) with each mode's
Laplace covariance as the inverse mass matrix (the posterior's scale in
every direction, so no mass-matrix adaptation from scratch is needed;
applied as a linear change of variables, see :func:`run_kalman_nuts`); the
step size is tuned by dual averaging (Hoffman & Gelman 2014, §3.2) towards
an acceptance statistic of 0.8 during warm-up, then frozen at its average.
"""

from __future__ import annotations

import functools
import time as _time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.compile import Bound, jit
from latentforce.inference.kalman_mcmc import (
    Initial,
    MCMCOutput,
    finish,
    log_posterior_fn,
    sample_in_chunks,
    start_chains,
)
from latentforce.models import LatentForceModel

TARGET_ACCEPTANCE = 0.8
MAX_DOUBLINGS = 8


class NUTSChain(NamedTuple):
    """One chain: blackjax's HMC state in whitened coordinates ``z`` with ``x = shift + root z``,
    and the dual-averaging state."""

    hmc: object
    da: object
    shift: jax.Array
    root: jax.Array


def forward_mode_density(logdensity: Callable) -> Callable:
    """``logdensity(x)`` whose reverse-mode gradient is computed by forward mode (module doc)."""

    @jax.custom_vjp
    def f(x):
        return logdensity(x)

    def fwd(x):
        value = logdensity(x)
        grad = jax.jacfwd(logdensity)(x)
        return value, grad

    def bwd(grad, g):
        return (g * grad,)

    f.defvjp(fwd, bwd)
    return f


def _whitened(logpost: Bound, shift, root, y, mask):
    return forward_mode_density(lambda z: logpost(shift + root @ z, y, mask))


@jit
def _init_chains(logpost: Bound, x, roots, y, mask):
    """Each chain's NUTS state at its start, in the whitened coordinates."""
    from blackjax.adaptation.step_size import dual_averaging_adaptation
    from blackjax.mcmc import nuts

    da_init = dual_averaging_adaptation(TARGET_ACCEPTANCE)[0]

    def one(xi, ri):
        # A first step of half the Laplace sd (one unit of z is one sd).
        return NUTSChain(nuts.init(jnp.zeros_like(xi), _whitened(logpost, xi, ri, y, mask)), da_init(0.5), xi, ri)

    return jax.vmap(one)(x, roots)


@functools.partial(jit, static_argnames=("n_chunk",))
def _run_chains(logpost: Bound, keys, s, adapt, y, mask, *, n_chunk: int):
    """``n_chunk`` NUTS iterations of every chain (vmapped); the step size adapted while ``adapt``."""
    from blackjax.adaptation.step_size import dual_averaging_adaptation
    from blackjax.mcmc import nuts

    _, da_update, da_final = dual_averaging_adaptation(TARGET_ACCEPTANCE)
    kernel = nuts.build_kernel()

    def chain(kc, sc):
        density = _whitened(logpost, sc.shift, sc.root, y, mask)
        unit_mass = jnp.ones(sc.shift.shape[-1])

        def step(c, k):
            step_size = jnp.where(adapt, jnp.exp(c.da.log_step_size), da_final(c.da))
            hmc, info = kernel(k, c.hmc, density, step_size, unit_mass, max_num_doublings=MAX_DOUBLINGS)
            acc = jnp.where(jnp.isfinite(info.acceptance_rate), info.acceptance_rate, 0.0)
            da = jax.tree_util.tree_map(lambda new, old: jnp.where(adapt, new, old), da_update(c.da, acc), c.da)
            stats = {
                "accepted": acc,
                "logdensity": hmc.logdensity,
                "steps": info.num_integration_steps,
                "divergent": info.is_divergent,
            }
            return c._replace(hmc=hmc, da=da), (c.shift + c.root @ hmc.position, stats)

        return jax.lax.scan(step, sc, jax.random.split(kc, n_chunk))

    s, (xs, stats) = jax.vmap(chain)(keys, s)
    return s, xs, stats


def run_kalman_nuts(
    key,
    model: LatentForceModel,
    fixed: dict,
    free: dict,
    y,
    mask,
    dt: float,
    *,
    iterations: int | None,
    burn_in: int,
    chains: int,
    initial: Initial | None = None,
    progress: Callable | None = None,
    chunk: int = 100,
    target_ess: float = 400,
    max_time: float = 600.0,
    checkpoint=None,
    kalman: str = "auto",
) -> MCMCOutput:
    """NUTS over the ``free`` parameters; arguments and output as
    :func:`~latentforce.inference.kalman_mcmc.run_kalman_mcmc`.

    ``MCMCOutput.accepted`` holds NUTS's acceptance statistic per draw,
    ``proposal_scale`` the step sizes, ``sampler_info`` the mean number of
    integration steps and the divergences.
    """

    t0 = _time.perf_counter()
    names = tuple(free)
    priors = tuple(free[n][0] for n in names)
    inits = np.array([float(free[n][1]) for n in names])
    logpost = log_posterior_fn(model, fixed, names, priors, dt, initial, bool(np.all(mask)), kalman=kalman)
    data = (jnp.asarray(np.where(mask, y, 0.0)), jnp.asarray(mask))
    key_start, key_run = jax.random.split(key)
    x0, covs, start, _ = start_chains(key_start, logpost, data, inits, priors, chains)
    # The Laplace covariance as a dense mass matrix, applied as the change of variables
    # x = shift + root z with an identity mass for z: the same dynamics, and the square
    # root taken here (NumPy) keeps LAPACK out of the vmapped program (cf. latentforce.linalg).
    roots = np.stack([np.linalg.cholesky(c) for c in covs])
    states = _init_chains(logpost, jnp.asarray(x0), jnp.asarray(roots), *data)
    n_chunk = max(1, min(chunk, burn_in or chunk, iterations or chunk))
    burn_total = -(-burn_in // n_chunk) * n_chunk

    def run_chunk(keys, s, start_step, adapt):
        return _run_chains(logpost, keys, s, adapt, *data, n_chunk=n_chunk)

    states, xs, stats, burn_total = sample_in_chunks(
        key_run,
        states,
        run_chunk,
        names,
        priors,
        chains=chains,
        n_chunk=n_chunk,
        burn_total=burn_total,
        iterations=iterations,
        target_ess=target_ess,
        max_time=max_time,
        t0=t0,
        progress=progress,
        checkpoint=checkpoint,
        sampler="kalman-nuts",
    )
    draws, loglik, record = finish(xs, stats["logdensity"], names, priors, target_ess)
    step_sizes = np.exp(np.asarray(states.da.log_step_size_avg))
    info = {
        "mean_integration_steps": float(np.mean(stats["steps"])),
        "divergences": int(np.sum(stats["divergent"])),
        "step_size": step_sizes.tolist(),
        "target_acceptance": TARGET_ACCEPTANCE,
    }
    return MCMCOutput(
        names,
        draws,
        stats["accepted"],
        loglik,
        stats["accepted"].mean(axis=1),
        step_sizes,
        _time.perf_counter() - t0,
        record,
        start,
        burn_total,
        info,
    )
