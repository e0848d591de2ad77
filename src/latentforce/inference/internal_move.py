r"""The internal states' start-up move: a hysteretic force's initial value stepped with the measured
motion held.

**Why.** On the Bouc-Wen oscillator with a smooth force (Matérn-3/2, 5/2), acceleration and
displacement measured, the slowest quantities of a ``pgas`` run are at the record's start: the
initial hysteretic force :math:`r_0` traded against the force (the acceleration fixes
:math:`u_0 - r_0`, the displacement fixes :math:`z`; docs/nonlinear.md, "Where the smooth-force
Bouc-Wen chains are slow"). The residual-preserving move has :math:`r_0` among its coordinates but
holds the displacements' within-step noise, so an offset of :math:`r` lets the motion drift within
each step and the displacement channel pins it: at posterior paths the conditional sd of
:math:`r_0` in those coordinates was 0.01-0.4 N against a posterior sd of 9 N. Holding the
displacements and velocities themselves (the system move's coordinates,
:meth:`~latentforce.inference.path_moves.ResidualMove.builder` with ``kinematic``) the
conditional sd was 8.7-9.4 N: as wide as the posterior.

**The move.** At fixed parameters, hold the displacements and velocities, the accelerometers'
residuals, the internal states' within-step noise and the force derivatives' remainders, and
step the internal states' initial offsets (their coordinates :math:`w_1` in units of their
initial prior's sd); the path is rebuilt by the kinematic map: :math:`r` follows its own
dynamics from the new start, and the force takes up the change. For fixed parameters that map
is a bijection of constant Jacobian (:mod:`latentforce.inference.system_moves`), and the step is
a translation of one held coordinate, so a symmetric proposal is accepted with the latent's
prior density ratio times the likelihood ratio (only channels that see neither the motion nor
the accelerations can change).

**Proposal.** A random walk shaped by the Gauss-Newton covariance of these coordinates, computed at
the path with the internal states' initial values at their prior mean and everything else held:
a function of the held coordinates alone, which no step of the move changes, so each step is a
Metropolis step with a fixed symmetric proposal (no Hastings correction, no adaptation). Needed:
the conditional sd of the Bouc-Wen record's r0 was 9 N at Matérn-3/2 but 0.2-0.7 N at Matérn-5/2
(the force's held derivative remainders then tie it), so no fixed scale serves both. Its
multiples alternate between :data:`SCALES`. Skipped where the system has no internal state or no
channel sees the force (:attr:`ResidualMove.applies`); by ``pgas`` where the initial prior ties
the internal states to the displacements and velocities (:func:`free`) and where system
parameters are sampled (the system move's walk then carries these initial values with the
parameters: :mod:`latentforce.inference.system_moves`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.inference import particle_model
from latentforce.inference.latent import ObservationDensity, _whiten, observation_log_likelihood
from latentforce.inference.path_moves import ResidualMove, gauss_newton_covariance, residual_log_target
from latentforce.linalg import cholesky

#: the chain key's fold for this move's random numbers (a run without it draws what it drew before)
INTERNAL_STREAM = 0x4953

#: the proposal's multiples of the Gauss-Newton covariance's Cholesky factor, used in turn: 2.4 the
#: random walk's optimum for one Gaussian coordinate, 0.8 for where the linearisation at the prior
#: mean is too wide (a kink of the hysteresis at r = 0, the virgin state)
SCALES = (2.4, 0.8)


#: below this share of their prior variance left free by the displacements and velocities, the
#: internal states' initial values are tied to the motion (see :func:`free`)
TIED = 1e-8


def applies(pm: particle_model.ParticleModel, rm: ResidualMove) -> bool:
    """Whether the move can run: the system has internal states and some channel sees the force."""
    return bool(rm.applies) and pm.internal.size > 0


def free(pm: particle_model.ParticleModel) -> bool:
    """Whether the initial prior (``pm.mech0_cov``, concrete) leaves some internal state's initial
    value free given the initial displacements and velocities: its conditional variance above
    :data:`TIED` of its marginal one. Not so without hysteresis (the default start then sets
    ``r = alpha z`` exactly, ``models.LatentForceModel.default_initial``): the move would step a
    coordinate of zero prior width, rebuilding the path ten times an iteration to change nothing
    (measured: the Bouc-Wen linear twin's pgas test 51-62 s -> 98 s with it)."""
    return bool(np.any(free_share(pm) > TIED))


def free_share(pm: particle_model.ParticleModel) -> np.ndarray:
    """Each internal state's conditional variance given the initial displacements and velocities
    under the initial prior (``pm.mech0_cov``, concrete), as a share of its marginal variance."""
    k = 2 * pm.ndof
    P = np.asarray(pm.mech0_cov, dtype=float)
    A, B, C = P[:k, :k], P[k:, :k], P[k:, k:]
    cond = np.diagonal(C - B @ np.linalg.pinv(A, hermitian=True) @ B.T)
    return np.clip(cond, 0.0, None) / np.maximum(np.diagonal(C), np.finfo(float).tiny)


def internal_move(
    key: Array,
    rm: ResidualMove,
    pm: particle_model.ParticleModel,
    od: ObservationDensity,
    tr: particle_model.Transition,
    path: Float[Array, "T n"],
    n_steps: int,
) -> tuple[Float[Array, "T n"], Float[Array, " n_steps"]]:
    """``n_steps`` Metropolis steps on the internal states' initial offsets (module doc), ``tr`` the
    transition of ``pm`` at the chain's hyperparameters. Returns the path (bit-for-bit the input
    when nothing was accepted) and the acceptances."""
    internal = pm.internal
    idx = jnp.asarray(rm.K * pm.nm + internal)
    build = rm.builder(pm, od, tr, path, kinematic=True)
    cP, cQ = particle_model._chol(tr.Pinf), particle_model._chol(tr.Q)
    scales = jnp.asarray(SCALES)
    ld0 = -0.5 * jnp.sum(_whiten(tr, pm.latent(path), cP, cQ) ** 2) + observation_log_likelihood(pm, od, path)
    chol = _shape(rm, pm, od, tr, path, build, idx, internal, cP, cQ)

    def _one(carry, inp):
        c, ld, x = carry
        k, s = inp
        k_prop, k_acc = jax.random.split(k)
        step = scales[s % scales.shape[0]] * (chol @ jax.random.normal(k_prop, idx.shape))
        prop = c.at[idx].add(step)
        ld_p, x_p = residual_log_target(tr, pm, od, build, prop, cP, cQ)
        accept = jnp.isfinite(ld_p) & (jnp.log(jax.random.uniform(k_acc)) < ld_p - ld)
        keep = lambda new, old: jnp.where(accept, new, old)  # noqa: E731
        return (keep(prop, c), keep(ld_p, ld), keep(x_p, x)), accept

    c0 = jnp.zeros(rm.dim)
    (_, _, path), accepted = jax.lax.scan(
        _one, (c0, ld0, path), (jax.random.split(key, int(n_steps)), jnp.arange(int(n_steps)))
    )
    return path, accepted


def _shape(rm, pm, od, tr, path, build, idx, internal, cP, cQ) -> Float[Array, "d d"]:
    """Cholesky factor of the Gauss-Newton covariance of the internal states' initial offsets at
    the reference path (module doc): their initial values at the prior mean, the held coordinates
    as they are."""
    c_ref = jnp.zeros(rm.dim).at[idx].set((pm.mech0_mean[internal] - path[0, internal]) / rm.scale_0[internal])
    return cholesky(gauss_newton_covariance(pm, od, tr, build, lambda a: c_ref.at[idx].add(a), idx.shape[0], cP, cQ))
