r"""The sensors' inferred noise levels in particle Gibbs: one exact Gibbs update per channel given the path.

A channel :math:`c` with an inferred ``noise_std`` :math:`s_c` (a prior
table in the config, the parameter ``noise_std_<column>``) has the noise
variance :math:`v_c = (\kappa_c s_c)^2` in SI, :math:`\kappa_c` the channel's
``noise_scale`` (SI per unit of the parameter, :mod:`latentforce.io.channels`).
Given the state path, the channels are independent (``R`` is diagonal) and
the conditional of :math:`v_c` is its prior times

.. math:: p(y_c \mid x_{1:T}, v_c) \propto v_c^{-n_c/2} \exp\bigl(-S_c / (2 v_c)\bigr),

:math:`n_c` the channel's observed samples and :math:`S_c` the sum of its
squared residuals :math:`y_t - c(\mathrm{mech}_t) - D x_{f,t}` over them
(:func:`~latentforce.inference.latent.observation_residuals`, the observation
log-likelihood's own residuals). As a density in :math:`v_c` that factor is
:math:`\mathrm{InvGamma}(n_c/2 - 1, S_c/2)` (proper for :math:`n_c > 2`), so
proposing from it and accepting with the ratio of the prior densities of
:math:`v_c` at the new and old values (independence Metropolis-Hastings) is
an exact update. The prior is on :math:`s_c`; its density on the variance is
:math:`p_s(\sqrt{v})/(2\sqrt{v})` (the constant :math:`\kappa_c` cancels in the ratio).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.inference import particle_model
from latentforce.inference.latent import ObservationDensity, observation_residuals

#: folded into a chain's key for its noise draws (only where some noise is inferred, so that
#: a run with every noise fixed draws exactly what it drew before noise levels were sampled)
NOISE_STREAM = 0x4E015E


class NoiseLevels(NamedTuple):
    """The channels whose noise level is inferred (empty: every noise fixed)."""

    names: tuple[str, ...] = ()  # parameter names, noise_std_<column>
    channels: tuple[int, ...] = ()  # their columns of y
    priors: tuple = ()  # priors on the noise standard deviation (the parameter's unit)
    scales: tuple[float, ...] = ()  # SI per unit of the parameter (the sensor's noise_scale)
    init: tuple[float, ...] = ()  # starting standard deviations (the parameter's unit)


# a pytree whose numbers (the priors' and the starting values) are leaves and whose names, columns
# and units are static: a compiled program that takes it serves every prior and start
jax.tree_util.register_pytree_node(
    NoiseLevels,
    lambda nl: ((nl.priors, nl.init), (nl.names, nl.channels, nl.scales)),
    lambda aux, ch: NoiseLevels(aux[0], aux[1], ch[0], aux[2], ch[1]),
)


def noise_levels(model, free: dict, mask=None) -> NoiseLevels:
    """The model's sensors whose ``noise_param`` is in ``free`` (``name -> (prior, init)``).

    With ``mask`` (``(T, d)``, the observed samples), each must have more than two
    observed samples (the conditional of its variance is proper only then).
    """
    rows = [
        (s.noise_param, i, free[s.noise_param][0], float(s.noise_scale), float(free[s.noise_param][1]))
        for i, s in enumerate(model.sensors)
        if s.noise_param in free
    ]
    if not rows:
        return NoiseLevels()
    if mask is not None:
        n = np.sum(np.asarray(mask, dtype=bool), axis=0)
        few = [f"{name} ({int(n[i])} observed samples)" for name, i, *_ in rows if n[i] <= 2]
        if few:
            raise ValueError(
                f"an inferred noise level needs more than two observed samples of its channel: {', '.join(few)}"
            )
    bad = [name for name, *_, init in rows if not init > 0]
    if bad:
        raise ValueError(f"initial noise levels must be positive: {bad}")
    return NoiseLevels(*(tuple(col) for col in zip(*rows)))


def initial_variances(nl: NoiseLevels, R: Float[Array, "d d"]) -> Float[Array, " d"]:
    """The channels' noise variances (SI) at the start: ``R``'s diagonal, the inferred ones at their ``init``."""
    var = jnp.diagonal(jnp.asarray(R, dtype=float))
    if nl.channels:
        var = var.at[jnp.asarray(nl.channels)].set((jnp.asarray(nl.init) * jnp.asarray(nl.scales)) ** 2)
    return var


def standard_deviations(nl: NoiseLevels, var: Float[Array, " d"]) -> Float[Array, " m"]:
    """The inferred channels' noise standard deviations in the parameters' units."""
    return jnp.sqrt(var[jnp.asarray(nl.channels, dtype=int)]) / jnp.asarray(nl.scales, dtype=float)


def _log_prior_variance(nl: NoiseLevels, var: Float[Array, " m"]) -> Float[Array, " m"]:
    r"""Log prior density of each inferred channel's variance in the parameter's unit, :math:`p_s(s)/(2s)`."""
    s = jnp.sqrt(var) / jnp.asarray(nl.scales, dtype=float)
    return jnp.stack([prior.log_prob(s[i]) for i, prior in enumerate(nl.priors)]) - jnp.log(2.0 * s)


def gibbs_step(
    key: Array,
    nl: NoiseLevels,
    pm: particle_model.ParticleModel,
    od: ObservationDensity,
    path: Float[Array, "T n"],
    var: Float[Array, " d"],
) -> tuple[Float[Array, " d"], Array]:
    """One exact update of each inferred channel's noise variance given ``path`` (module doc).

    ``var``: every channel's noise variance (SI); returns the updated ones and
    whether each inferred channel's proposal was accepted. ``od`` supplies the
    record and its mask only (its noise terms are not used).
    """
    idx = jnp.asarray(nl.channels, dtype=int)
    r = observation_residuals(pm, od, path)
    S = jnp.sum(r**2, axis=0)[idx]
    n = jnp.sum(od.maskf, axis=0)[idx]
    k_prop, k_acc = jax.random.split(key)
    prop = 0.5 * S / jax.random.gamma(k_prop, 0.5 * n - 1.0, dtype=var.dtype)
    old = var[idx]
    log_ratio = _log_prior_variance(nl, prop) - _log_prior_variance(nl, old)
    # a non-finite ratio (a proposal outside the prior's support, or a degenerate draw) is a rejection
    accept = (jnp.log(jax.random.uniform(k_acc, idx.shape, dtype=var.dtype)) < log_ratio) & (prop > 0)
    return var.at[idx].set(jnp.where(accept, prop, old)), accept
