r"""Metropolis-within-Gibbs for the GP hyperparameters given the path (Eq. 23-25, Vibration 2020):
the centred step on the latent path's density and the non-centred (interweaving, Yu & Meng 2011)
step on the whitened innovations; the sampling space and its adaptation are described in
:mod:`latentforce.inference.pgas`."""

from __future__ import annotations

import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.inference import mcmc, particle_model
from latentforce.inference.latent import (
    ObservationDensity,
    colour,
    latent_log_density,
    observation_log_likelihood,
)
from latentforce.priors import log_prob_coordinate, to_coordinate, to_value

# fractions of the burn-in MH steps after which the proposal shape is re-estimated
_RESHAPE_AT = (0.05, 0.1, 0.2, 0.4, 0.7)
HYPERPARAMETERS = ("force_variance", "force_lengthscale")


def gp_path_log_density(
    pm: particle_model.ParticleModel, variance, lengthscale, g: Float[Array, "T nl"]
) -> Float[Array, ""]:
    r""":math:`\log p(g_{1:T} \mid \theta)` of the latent path (force states and within-step
    mechanical noise, :mod:`particle_model`), vectorised over time (no scan)."""
    return latent_log_density(pm.transition(variance, lengthscale), g)


@jax.tree_util.register_pytree_node_class
class Hyper:
    r"""Which parameters the Gibbs chain samples besides the noise levels, their priors, and the fixed values.

    ``names``: the free GP hyperparameters (the centred, non-centred and joint moves sample
    them). ``sys_names``: the free system parameters (``m, c, k, k3`` ..., any of the
    ``system_names`` the caller allows), moved with the path and the hyperparameters by the
    joint move only (:func:`latentforce.inference.smoother_move.joint_move`): given a path the
    within-step noise pins them, and only a move that redraws the path with them mixes. The
    joint move's coordinates are ``(x, x_sys)``, hyperparameters first.

    The sampling coordinates are :math:`x = \log\theta` (module doc), except a system parameter
    that may take either sign under its prior (:class:`latentforce.priors.SignedNormal`: ``k3``,
    ``beta``, ``gamma``), whose coordinate is its standardised value. A pytree: the names are static, the
    priors' numbers, the starting values and the fixed values are leaves (a compiled program
    that takes it serves every value).
    """

    def __init__(
        self,
        params: dict,
        free: dict,
        system_names: tuple[str, ...] = (),
        hyper_names: tuple[tuple[str, ...], tuple[str, ...]] = ((HYPERPARAMETERS[0],), (HYPERPARAMETERS[1],)),
    ):
        # hyper_names: (variance names, lengthscale names), one each per kernel term
        # (models.hyper_names(kernel, split=True))
        self.var_names, self.ls_names = tuple(hyper_names[0]), tuple(hyper_names[1])
        all_hyper = self.var_names + self.ls_names
        bad = [n for n in free if n not in all_hyper and n not in system_names]
        if bad:
            raise ValueError(f"PGAS samples only {all_hyper + tuple(system_names)}; cannot sample {bad}")
        self.names = tuple(n for n in all_hyper if n in free)
        self.sys_names = tuple(n for n in system_names if n in free and n not in all_hyper)
        self.priors = tuple(free[n][0] for n in self.names)
        self.sys_priors = tuple(free[n][0] for n in self.sys_names)
        self.init = np.array([float(free[n][1]) for n in self.names], dtype=float)
        self.sys_init = np.array([float(free[n][1]) for n in self.sys_names], dtype=float)
        for names, init, priors in (
            (self.names, self.init, self.priors),
            (self.sys_names, self.sys_init, self.sys_priors),
        ):
            bad = {n: v for n, v, prior in zip(names, init, priors) if not (np.isfinite(v) and (prior.signed or v > 0))}
            if bad:
                raise ValueError(f"initial values of sampled parameters must be positive and finite, got {bad}")
        self.fixed = {n: float(params[n]) for n in all_hyper}

    def tree_flatten(self):
        return (self.priors, self.init, self.fixed, self.sys_priors, self.sys_init), (
            self.names,
            self.sys_names,
            self.var_names,
            self.ls_names,
        )

    @classmethod
    def tree_unflatten(cls, names, children):
        hyper = object.__new__(cls)
        hyper.names, hyper.sys_names, hyper.var_names, hyper.ls_names = names
        hyper.priors, hyper.init, hyper.fixed, hyper.sys_priors, hyper.sys_init = children
        return hyper

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The joint move's coordinates by name: the hyperparameters, then the system parameters."""
        return self.names + self.sys_names

    def system_values(self, x_sys: Float[Array, " s"]) -> dict:
        """The system parameters by name at the unconstrained ``x_sys``."""
        return {
            n: to_value(prior, x_sys[..., i], "log")
            for i, (n, prior) in enumerate(zip(self.sys_names, self.sys_priors))
        }

    def system_array(self, x_sys: Float[Array, "... s"]) -> Float[Array, "... s"]:
        """The system parameters' values at ``x_sys`` (last axis: ``sys_names``)."""
        values = self.system_values(x_sys)
        return jnp.stack([values[n] for n in self.sys_names], axis=-1) if self.sys_names else jnp.zeros(x_sys.shape)

    def joint_values(self, x: Float[Array, "... q"]) -> Float[Array, "... q"]:
        """The joint move's values ``(theta, theta_sys)`` at its coordinates ``(x, x_sys)``."""
        p = len(self.names)
        return jnp.concatenate([self.to_constrained(x[..., :p]), self.system_array(x[..., p:])], axis=-1)

    def joint_coordinates(self, theta: Float[Array, "... q"]) -> Float[Array, "... q"]:
        """The joint move's coordinates at the values ``theta`` (inverse of :meth:`joint_values`)."""
        theta = jnp.asarray(theta, dtype=float)
        p = len(self.names)
        sys = [to_coordinate(prior, theta[..., p + i], "log") for i, prior in enumerate(self.sys_priors)]
        return jnp.concatenate([self.to_unconstrained(theta[..., :p])] + [v[..., None] for v in sys], axis=-1)

    def model_at(self, pm: particle_model.ParticleModel, x_sys: Float[Array, " s"]) -> particle_model.ParticleModel:
        """``pm`` at the system parameters ``x_sys`` (``pm`` itself when none is sampled)."""
        return pm.with_params(self.system_values(x_sys)) if self.sys_names else pm

    def joint_log_prior(self, x: Float[Array, " q"]) -> Float[Array, ""]:
        """The prior density of the joint move's coordinates ``(x, x_sys)`` (log space, Jacobians included)."""
        p = len(self.names)
        lp = self.log_prior(x[:p])
        for i, prior in enumerate(self.sys_priors):
            lp = lp + log_prob_coordinate(prior, x[p + i], "log")
        return lp

    @staticmethod
    def to_unconstrained(theta: Float[Array, " p"]) -> Float[Array, " p"]:
        r""":math:`x = \log\theta` (the sampling coordinates)."""
        return jnp.log(jnp.asarray(theta, dtype=float))

    @staticmethod
    def to_constrained(x: Float[Array, " p"]) -> Float[Array, " p"]:
        r""":math:`\theta = e^x`."""
        return jnp.exp(jnp.asarray(x, dtype=float))

    def values(self, x: Float[Array, " p"]):
        """``(variance, lengthscale)`` from the unconstrained vector ``x``: scalars for a Matérn,
        one entry per term of a kernel sum."""
        vals = dict(self.fixed)
        theta = self.to_constrained(x)
        for i, n in enumerate(self.names):
            vals[n] = theta[i]
        if len(self.var_names) == 1:
            return jnp.asarray(vals[self.var_names[0]], dtype=float), jnp.asarray(vals[self.ls_names[0]], dtype=float)
        stack = lambda names: jnp.stack([jnp.asarray(vals[n], dtype=float) for n in names])
        return stack(self.var_names), stack(self.ls_names)

    def log_prior(self, x: Float[Array, " p"]) -> Float[Array, ""]:
        r""":math:`\sum_i \log p(\theta_i) + x_i`: the prior density of :math:`x = \log\theta`."""
        theta = self.to_constrained(x)
        lp = jnp.zeros(())
        for i, prior in enumerate(self.priors):
            lp = lp + prior.log_prob(theta[i]) + x[i]
        return lp

    def log_target(self, pm, x: Float[Array, " p"], g: Float[Array, "T nl"]) -> Float[Array, ""]:
        """Centred MH target in log space: prior + log-Jacobian + latent path density (module doc)."""
        return self.log_target_and_transition(pm, x, g)[0]

    def log_target_and_transition(
        self, pm, x: Float[Array, " p"], g: Float[Array, "T nl"]
    ) -> tuple[Float[Array, ""], particle_model.Transition]:
        """:meth:`log_target` and the latent's transition at ``x`` (which the sampler carries)."""
        tr = pm.transition(*self.values(x))
        return self.log_target_given(tr, x, g), tr

    def log_target_given(
        self, tr: particle_model.Transition, x: Float[Array, " p"], g: Float[Array, "T nl"]
    ) -> Float[Array, ""]:
        """:meth:`log_target` when ``tr``, the transition at ``x``, is already known."""
        return self.log_prior(x) + latent_log_density(tr, g)


def init_proposal(
    hyper: Hyper, log_target: Callable, x: Float[Array, " p"], proposal_sd: float = 0.05
) -> mcmc.RWMState:
    """Start the hyperparameter random walk at ``x`` with a diagonal proposal (log space)."""
    return mcmc.init(x, log_target, jnp.full(x.shape, proposal_sd))


def adaptation_schedule(burn_in_steps: int) -> tuple[int, ...]:
    """MH step numbers (0-based, burn-in) after which the proposal shape is reset (module doc)."""
    out = sorted({int(math.ceil(f * burn_in_steps)) - 1 for f in _RESHAPE_AT})
    return tuple(s for s in out if s >= 9)  # at least ten steps in the first window


def mh_step(
    key: Array,
    state: mcmc.RWMState,
    log_target: Callable,
    *,
    adapt: Array,
    reshape: Array,
    target: float,
    aux=None,
    adapt_density: Callable | None = None,
):
    """One random-walk MH step on the hyperparameters (``mcmc.step``), adaptive only where ``adapt``.

    ``state.logdensity`` must be ``log_target(state.x)`` (refresh it when the
    conditioning path changes). ``reshape``: reset the proposal shape from
    the running covariance, then restart the running moments. A non-finite
    proposed target is a rejection (never a propagated NaN). With ``aux``,
    as :func:`mcmc.step` (the target returns ``(log density, aux)``), and so ``adapt_density``.
    """
    out = mcmc.step(key, state, log_target, adapt, reshape & adapt, target, aux, adapt_density=adapt_density)
    restart = reshape & adapt
    state = out[0]._replace(mean=jnp.where(restart, out[0].x, out[0].mean), count=jnp.where(restart, 0.0, out[0].count))
    return (state,) + tuple(out[1:])


def proposal_covariance(state: mcmc.RWMState) -> Float[Array, "p p"]:
    """The (frozen after burn-in) random-walk covariance :math:`s^2 L L^\\top` in log space."""
    return jnp.exp(2.0 * state.log_scale) * state.chol @ state.chol.T


def noncentred_log_target(
    hyper: Hyper,
    pm: particle_model.ParticleModel,
    od: ObservationDensity,
    x: Float[Array, " p"],
    eps: Float[Array, "T nl"],
) -> tuple[Float[Array, ""], tuple[Float[Array, "T nl"], Float[Array, "T n"], particle_model.Transition]]:
    r"""Target of :math:`x = \log\theta` given the latent's innovations; the rebuilt latent, path and transition.

    :math:`\log p(\theta) + \sum_i x_i + \log p(y \mid x_{1:T}(\theta, \varepsilon))`:
    the innovations' density does not depend on :math:`\theta` and, the
    innovations being held fixed, there is no path Jacobian. Returns
    ``(log target, (latent, path, transition at theta))``.
    """
    tr = pm.transition(*hyper.values(x))
    g = colour(tr, eps)
    path = pm.path(g)
    return hyper.log_prior(x) + observation_log_likelihood(pm, od, path), (g, path, tr)
