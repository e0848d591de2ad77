r"""Independence proposals from the posterior's Laplace approximation (for ``kalman-mcmc``).

On a long record the parameter posterior is close to the Gaussian that the
optimiser's Laplace approximation fits (:mod:`latentforce.inference.laplace`),
and a random walk, however well shaped, still needs about :math:`p/0.3`
iterations per effective draw in :math:`p` dimensions (measured: 29 200
draws for a bulk ESS of 590 on the 3-DOF frame, :math:`p = 8`). An
*independence* Metropolis-Hastings step (Tierney 1994) proposes from a fixed
density :math:`q` that does not depend on the chain's position,

.. math::
    x' \sim q, \qquad
    \alpha = \min\Big\{1, \frac{\pi(x')\,q(x)}{\pi(x)\,q(x')}\Big\},

so an accepted proposal is a fresh, independent draw. Here :math:`q` is a
mixture, over the modes the optimiser found (weighted by their Laplace
mass), of multivariate Student-t densities with :data:`DF` degrees of
freedom and scale :data:`SCALE` times the mode's Laplace covariance: the
t's polynomial tails keep :math:`\pi/q` bounded where the posterior is
heavier-tailed than a Gaussian, the inflation covers a Laplace covariance
that is somewhat too narrow, and with several modes the chain can jump
between them, which a random walk cannot. (A Gaussian target in 8
dimensions with the exact covariance: acceptance about 0.6 and an effective
sample size per iteration about 0.45; with the mean 0.3 sd off and the sds
20 % off, still 0.2-0.3: against 0.02 for the adapted random walk.)

:func:`latentforce.inference.mcmc.step` mixes this step with the random
walk, choosing it with a probability set during the warm-up from its own
acceptance rate and then frozen, so the post-warm-up chain is a fixed
mixture of two Metropolis-Hastings kernels that each leave the posterior
invariant, and targets it exactly. Where the Laplace fit is poor the
independence step is chosen rarely and the random walk carries the chain.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln, logsumexp
from jaxtyping import Array, Float

#: degrees of freedom of the Student-t components
DF = 10.0
#: the components' scale, relative to each mode's Laplace standard deviations
SCALE = 1.25
#: modes whose Laplace mass is below the best's by more than this (in log) are left out
MAX_LOG_MASS_GAP = 10.0
#: bounds of the probability of choosing the independence step, set from its warm-up acceptance
MIN_PROB, MAX_PROB = 0.1, 0.8


class IndependenceProposal(NamedTuple):
    """A mixture of multivariate t densities (arrays only: an argument of compiled programs)."""

    means: Float[Array, "K p"]
    chols: Float[Array, "K p p"]  # lower Cholesky factors of the components' scale matrices
    inv_chols: Float[Array, "K p p"]  # their inverses (no triangular solve inside the programs)
    log_weights: Float[Array, " K"]  # normalised
    log_dets: Float[Array, " K"]  # log |chol|
    df: Float[Array, ""]


def from_modes(
    modes, *, scale: float = SCALE, df: float = DF, max_log_mass_gap: float = MAX_LOG_MASS_GAP
) -> IndependenceProposal:
    """The proposal built from :class:`latentforce.inference.laplace.Mode` s (best first)."""
    kept = [m for m in modes if m.log_mass >= modes[0].log_mass - max_log_mass_gap]
    chols = np.stack([scale * np.linalg.cholesky(0.5 * (m.cov + m.cov.T)) for m in kept])
    log_w = np.array([m.log_mass for m in kept])
    log_w = log_w - (log_w.max() + np.log(np.sum(np.exp(log_w - log_w.max()))))
    return IndependenceProposal(
        jnp.asarray(np.stack([m.x for m in kept])),
        jnp.asarray(chols),
        jnp.asarray(np.linalg.inv(chols)),
        jnp.asarray(log_w),
        jnp.asarray(np.sum(np.log(np.abs(np.diagonal(chols, axis1=1, axis2=2))), axis=1)),
        jnp.asarray(float(df)),
    )


def log_density(prop: IndependenceProposal, x: Float[Array, " p"]) -> Float[Array, ""]:
    """Log density of the mixture at ``x`` (normalised)."""
    p = x.shape[-1]
    nu = prop.df
    delta = jnp.einsum("kij,kj->ki", prop.inv_chols, x[None, :] - prop.means)
    maha = jnp.sum(delta * delta, axis=-1)
    log_t = (
        gammaln(0.5 * (nu + p))
        - gammaln(0.5 * nu)
        - 0.5 * p * jnp.log(nu * jnp.pi)
        - prop.log_dets
        - 0.5 * (nu + p) * jnp.log1p(maha / nu)
    )
    return logsumexp(prop.log_weights + log_t)


def draw(key, prop: IndependenceProposal) -> Float[Array, " p"]:
    """One draw from the mixture: a component by weight, then ``mean + chol z sqrt(nu / chi2_nu)``."""
    k_comp, k_z, k_chi = jax.random.split(key, 3)
    p = prop.means.shape[-1]
    c = jax.random.categorical(k_comp, prop.log_weights)
    z = jax.random.normal(k_z, (p,), dtype=prop.means.dtype)
    chi2 = 2.0 * jax.random.gamma(k_chi, 0.5 * prop.df, dtype=prop.means.dtype)
    return prop.means[c] + jnp.sqrt(prop.df / chi2) * (prop.chols[c] @ z)


def choice_probability(accept_mean: Float[Array, ""], count: Float[Array, ""]) -> Float[Array, ""]:
    """Probability of taking the independence step: twice its mean warm-up acceptance, clipped to
    [:data:`MIN_PROB`, :data:`MAX_PROB`] (one half before it has been tried ten times).

    An accepted independence step is a fresh draw, worth far more than a
    random-walk step (about :math:`0.3/p` of one); the random walk keeps at
    least a fifth of the steps, for what the fit misses."""
    return jnp.where(count >= 10, jnp.clip(2.0 * accept_mean, MIN_PROB, MAX_PROB), 0.5)
