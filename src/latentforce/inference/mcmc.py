r"""Random-walk Metropolis with adaptation during burn-in only (pure, jittable).

The kernel follows Algorithm 1 of ISMA 2018: a Gaussian random walk
:math:`x' = x + s\,L\,\varepsilon` in the unconstrained (softplus) space,
accepted with probability :math:`\min\{1, \pi(x')/\pi(x)\}`.

Adaptation (burn-in only, so the post-burn-in chain is a plain Metropolis
chain with a fixed proposal and targets the posterior exactly):

* the global scale :math:`s` follows a Robbins-Monro recursion on
  :math:`\log s` towards the acceptance rate that is optimal for the
  dimension (0.44 in 1-D, 0.234 in many; Roberts & Rosenthal 2001);
* after a quarter of the burn-in, the proposal shape :math:`L` is the
  Cholesky factor of the running covariance of the chain (Haario, Saksman &
  Tamminen 2001), started from a diagonal guess. Where the state carries a
  prior guess of the covariance (``cov0``, e.g. a Laplace fit), it enters the
  reshaped covariance as :data:`PRIOR_WEIGHT` ``+ p`` pseudo-draws: a chain
  that moved little in some direction before the reshape then keeps a
  proposal there (without it a pgas chain's Bouc-Wen ``beta`` froze at
  R-hat 2.3: three accepted joint moves before the reshape, a covariance of
  rank two, a proposal sd of 0.03 in a posterior of sd 40).

With an ``independent`` proposal (:mod:`latentforce.inference.independence`,
the posterior's Laplace fit) each step is, with a probability fixed at the
end of the warm-up, an independence Metropolis-Hastings step instead of the
random walk: a mixture of two kernels that each leave the target invariant.

Pure functions in the house style: ``init(x, logdensity) -> RWMState``,
``step(key, state, logdensity, adapt) -> (RWMState, RWMInfo)``.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from latentforce.inference import independence
from latentforce.linalg import cholesky


class RWMState(NamedTuple):
    """One chain's position and its proposal adaptation statistics."""

    x: Float[Array, " p"]
    logdensity: Float[Array, ""]
    log_scale: Float[Array, ""]
    chol: Float[Array, "p p"]
    mean: Float[Array, " p"]  # running mean of x (adaptation)
    cov: Float[Array, "p p"]  # running covariance of x (adaptation)
    count: Float[Array, ""]  # number of adaptation updates so far
    # The independence step's warm-up acceptance (mean probability) and how often it was tried;
    # None where no independence proposal is used.
    imh_accept: Float[Array, ""] | None = None
    imh_count: Float[Array, ""] | None = None
    #: a prior guess of the target's covariance, kept in every reshape (module doc); None: none
    cov0: Float[Array, "p p"] | None = None
    #: the running (exponentially weighted) acceptance of the steps that adapt on
    #: ``adapt_density`` (:func:`step`'s floor); None: never adapted so
    acc_mean: Float[Array, ""] | None = None


#: pseudo-draws (besides the dimension) that a state's ``cov0`` counts for in a reshape
PRIOR_WEIGHT = 10.0

#: With ``adapt_density`` (:func:`step`), the least running acceptance of the step itself: under
#: twice this the scale's update is capped so that it shrinks the step below it.
ACCEPTANCE_FLOOR = 0.02
#: weight of one step in the running acceptance (about the last 50 steps)
ACCEPTANCE_MEMORY = 0.02


class RWMInfo(NamedTuple):
    accepted: Bool[Array, ""]
    logdensity: Float[Array, ""]
    independent: Bool[Array, ""] | None = None  # the step was an independence proposal


def target_acceptance(dim: int) -> float:
    """Asymptotically optimal random-walk acceptance rate for ``dim`` dimensions."""
    return 0.44 if dim == 1 else max(0.234, 0.44 - 0.06 * (dim - 1))


def init(x: Float[Array, " p"], logdensity: Callable, proposal_sd: Float[Array, " p"]) -> RWMState:
    """Start a chain at ``x`` with a diagonal proposal ``proposal_sd``."""
    ld = logdensity(x)
    return RWMState(
        x, ld, jnp.zeros(()), jnp.diag(proposal_sd), x, jnp.diag(proposal_sd**2), jnp.zeros(()), acc_mean=jnp.ones(())
    )


def step(
    key,
    state: RWMState,
    logdensity: Callable,
    adapt: Bool[Array, ""],
    adapt_shape: Bool[Array, ""],
    target: float,
    aux=None,
    independent: independence.IndependenceProposal | None = None,
    adapt_density: Callable | None = None,
):
    r"""One Metropolis step; adapts the proposal only where ``adapt`` is true.

    With ``independent`` (and ``state.imh_accept``, ``state.imh_count`` set),
    the step is an independence Metropolis-Hastings step with probability
    :func:`latentforce.inference.independence.choice_probability` of the
    independence step's warm-up acceptance (frozen with the rest of the
    adaptation), else the random walk; the random walk's scale adapts on its
    own steps only.

    A proposal whose log density is not finite (e.g. a NaN likelihood from an
    unstable parameter set) is rejected, never propagated (STYLE 12).
    Returns ``(state, info)``; with ``aux`` (a pytree belonging to the current
    point) ``logdensity`` returns ``(log density, aux)`` and the step returns
    ``(state, info, aux of the point kept)``, so that what the density
    computed on the way (e.g. a rebuilt path) need not be computed again.

    ``adapt_density`` (with ``aux``): the scale adapts on the acceptance probability of
    ``adapt_density(aux)``, a noiseless part of the log density, instead of the step's own. For a
    target estimated with noise (a pseudo-marginal step: a fresh random path at each proposal)
    whose acceptance stays below ``target`` at any step size, adapting on the step's own acceptance
    shrinks the step towards zero (:func:`latentforce.inference.smoother_move.joint_move`).
    Adaptation only: the step accepts on ``logdensity``. A floor keeps that proxy honest: where the
    noiseless part is much wider than the target (a loose expansion), its optimum would be a step
    the target almost never accepts; so once the step's own running acceptance (``acc_mean``, from
    :func:`init`) falls under twice :data:`ACCEPTANCE_FLOOR`, the update is capped at
    :math:`(1 - \text{target})(\bar a - f)/f`, which shrinks the step until it is accepted about
    as often as the floor :math:`f`.
    """
    p = state.x.shape[0]
    if independent is None:
        key_prop, key_acc = jax.random.split(key)
        use_ind = jnp.zeros((), bool)
    else:
        key_prop, key_acc, key_choice, key_ind = jax.random.split(key, 4)
        prob = independence.choice_probability(state.imh_accept, state.imh_count)
        use_ind = jax.random.uniform(key_choice, dtype=state.x.dtype) < prob
    eps = jax.random.normal(key_prop, (p,), dtype=state.x.dtype)
    x_new = state.x + jnp.exp(state.log_scale) * (state.chol @ eps)
    log_q_ratio = jnp.zeros((), state.x.dtype)
    if independent is not None:
        x_new = jnp.where(use_ind, independence.draw(key_ind, independent), x_new)
        # Hastings ratio q(x) / q(x'); zero for the (symmetric) random walk.
        log_q_ratio = jnp.where(
            use_ind, independence.log_density(independent, state.x) - independence.log_density(independent, x_new), 0.0
        )
    if aux is None:
        ld_new = logdensity(x_new)
    else:
        ld_new, aux_new = logdensity(x_new)
    ld_new = jnp.where(jnp.isfinite(ld_new), ld_new, -jnp.inf)
    log_alpha = jnp.minimum(ld_new - state.logdensity + log_q_ratio, 0.0)
    accepted = jnp.log(jax.random.uniform(key_acc, dtype=state.x.dtype)) < log_alpha
    x = jnp.where(accepted, x_new, state.x)
    ld = jnp.where(accepted, ld_new, state.logdensity)

    # Adaptation (burn-in only); the random walk's scale from its own steps.
    count = state.count + adapt
    gamma = jnp.where(adapt & ~use_ind, 1.0 / jnp.maximum(count, 1.0) ** 0.6, 0.0)
    alpha = jnp.exp(jnp.where(jnp.isfinite(log_alpha), log_alpha, -jnp.inf))
    signal = alpha - target
    acc_mean = state.acc_mean
    if adapt_density is not None:
        log_alpha_adapt = jnp.minimum(adapt_density(aux_new) - adapt_density(aux) + log_q_ratio, 0.0)
        ok = jnp.isfinite(log_alpha_adapt) & jnp.isfinite(ld_new)
        alpha_adapt = jnp.exp(jnp.where(ok, log_alpha_adapt, -jnp.inf))
        if acc_mean is None:
            raise ValueError("adapt_density needs a state from mcmc.init (its running acceptance, acc_mean)")
        acc_mean = acc_mean + jnp.where(gamma > 0.0, ACCEPTANCE_MEMORY * (alpha - acc_mean), 0.0)
        floor = (1.0 - target) * (acc_mean - ACCEPTANCE_FLOOR) / ACCEPTANCE_FLOOR
        signal = jnp.minimum(alpha_adapt - target, floor)
    log_scale = state.log_scale + gamma * signal
    imh_accept, imh_count = state.imh_accept, state.imh_count
    if independent is not None:
        imh_count = imh_count + (adapt & use_ind)
        imh_accept = imh_accept + jnp.where(adapt & use_ind, (alpha - imh_accept) / jnp.maximum(imh_count, 1.0), 0.0)
    w = jnp.where(adapt, 1.0 / (count + 1.0), 0.0)
    diff = x - state.mean
    mean = state.mean + w * diff
    cov = state.cov + w * (jnp.outer(diff, x - mean) - state.cov)
    # Reshape the proposal from the chain's covariance once enough is known (with the prior
    # guess's pseudo-draws, module doc).
    shape = cov
    if state.cov0 is not None:
        n0 = PRIOR_WEIGHT + p
        shape = (count * cov + n0 * state.cov0) / (count + n0)
    new_chol = cholesky(0.5 * (shape + shape.T) + 1e-12 * jnp.eye(p) * jnp.trace(shape) / p)
    use_new = adapt & adapt_shape & jnp.all(jnp.isfinite(new_chol))
    # Switching shape rescales: restart the scale near the optimal 2.38/sqrt(p).
    chol = jnp.where(use_new, new_chol * (2.38 / jnp.sqrt(p)), state.chol)
    log_scale = jnp.where(use_new, 0.0, log_scale)
    info = RWMInfo(accepted, ld) if independent is None else RWMInfo(accepted, ld, use_ind)
    out = RWMState(x, ld, log_scale, chol, mean, cov, count, imh_accept, imh_count, state.cov0, acc_mean), info
    if aux is None:
        return out
    return out + (jax.tree_util.tree_map(lambda a, b: jnp.where(accepted, a, b), aux_new, aux),)


def run_chain(
    key,
    state: RWMState,
    logdensity: Callable,
    n_steps: int,
    *,
    adapt,
    adapt_shape_at: tuple[int, ...] = (),
    target: float = 0.234,
    start=0,
    independent: independence.IndependenceProposal | None = None,
):
    """Scan ``n_steps`` Metropolis steps; returns the final state, draws and infos.

    ``adapt`` may be a traced boolean and ``start`` (the global number of the
    first step) a traced integer, so a long run is scanned in equal chunks
    (for progress reports) by ONE compiled program, burn-in and sampling
    alike. ``adapt_shape_at`` lists the global step numbers at which the
    proposal shape is reset from the running covariance (burn-in only).
    ``independent``: mix in independence steps (:func:`step`).
    """
    keys = jax.random.split(key, n_steps)
    steps = jnp.arange(n_steps) + start
    shape_steps = jnp.asarray(adapt_shape_at if adapt_shape_at else (-1,))

    def _step(s, inputs):
        k, i = inputs
        adapt_shape = jnp.any(i == shape_steps)
        s, info = step(k, s, logdensity, jnp.asarray(adapt), adapt_shape, target, independent=independent)
        return s, (s.x, info)

    state, (xs, infos) = jax.lax.scan(_step, state, (keys, steps))
    return state, xs, infos
