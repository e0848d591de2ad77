r"""The system parameters' move with the measured motion held: a nonlinear system's parameters
stepped with its path deformed so that the displacements, velocities and accelerometer residuals
are kept (the non-centred partner of the joint move).

**Why.** The joint move (:func:`latentforce.inference.smoother_move.joint_move`) proposes system
parameters with a new path drawn from the model linearised about a centre path, so it is as good
as that linearisation. Across a kink of the dynamics (Bouc-Wen's :math:`|r|` at :math:`r = 0`, its
:math:`|\dot z|` at every velocity reversal) it is poor: on the Bouc-Wen benchmark record with
gamma sampled and an initial hysteretic force straddling zero, each chain's gamma froze
(within-chain sd 3-20 against a posterior sd of 160, R-hat 3.9; docs/nonlinear.md, "gamma < 0").

**The move.** Coordinates of the latent path (:meth:`ResidualMove.builder` with ``kinematic``):
the displacements and velocities themselves, the internal (hysteretic) states' within-step noise,
the residuals :math:`\rho` of the channels that see the force, and the remainders :math:`h` of the
force derivatives' innovations. Hold them and step the system parameters :math:`x_s` (the joint
move's coordinates); the path at :math:`x_s'` is rebuilt by the same map under the model at
:math:`x_s'`: the motion stays, the force takes up the changed restoring force (:math:`u' \approx
u + \Delta r` for a Bouc-Wen gamma step), the displacements' and velocities' within-step noise
follows, and the force's prior, the within-step noise's density and the other channels'
likelihood decide. No linearisation enters. Holding the noise of every mechanical state instead
(the residual-preserving move's coordinates) lets the motion drift with a changed restoring force
within each step, and a displacement channel then pins the parameters (docs/nonlinear.md).

**Exactness.** For every :math:`x_s` the map :math:`F_{x_s}` from the coordinates to the latent
path is a bijection, triangular in time with diagonal blocks the identity (the held motion, the
internal noise, :math:`h`) and :math:`-D_S^{-1}(x_s)` (the force values from the residuals). So
the joint density of :math:`(x_s, \xi)` is :math:`\pi(x_s, F_{x_s}(\xi))\,|\det D_S^{-1}(x_s)|^T`,
and a symmetric random walk on :math:`x_s` at fixed :math:`\xi` is a Metropolis step on it:
accepted with the prior ratio times the latent's density ratio (its within-step noise covariance
depends on :math:`x_s`: log-determinants included) times the likelihood ratio times the Jacobian
ratio (1 unless the mass is sampled). Its scale adapts in burn-in only.

**The internal states' start.** Among the held coordinates are the internal states' initial
values, and the start-up move (:mod:`latentforce.inference.internal_move`) holds the system
parameters: on the Bouc-Wen benchmark record with gamma sampled and the default start, a chain
that reached gamma ~ -2 000 with r0 ~ +30-80 N (what such a gamma needs) stayed there for hundreds
of iterations, each move holding the other's coordinate (docs/nonlinear.md). With ``internal``
the walk is on both: the system parameters and the internal states' initial offsets (in the
initial prior's sds, :func:`internal_offsets`), one more translation of held coordinates, so the
Jacobian is unchanged and the target is the same; the offsets are read from the path at each call
(absolute, so the walk's running covariance learns their correlation with the parameters).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.inference import mcmc, particle_model
from latentforce.inference.hyper_moves import Hyper, mh_step
from latentforce.inference.latent import ObservationDensity, latent_log_density, observation_log_likelihood
from latentforce.inference.path_moves import ResidualMove
from latentforce.linalg import cholesky

#: the chain key's fold for this move's random numbers (a run without it draws what it drew before)
SYSTEM_STREAM = 0x5953


def _log_jacobian(rm: ResidualMove, T: int) -> Float[Array, ""]:
    """:math:`T \\log|\\det D_S^{-1}|` of the map at ``rm``'s model (module doc), as half the log
    determinant of :math:`D_S^{-\\top} D_S^{-1}` (our Cholesky: the compiled programs call no LAPACK)."""
    return T * jnp.sum(jnp.log(jnp.diagonal(cholesky(rm.Dinv.T @ rm.Dinv))))


def internal_coordinates(rm: ResidualMove, pm: particle_model.ParticleModel) -> np.ndarray:
    """The internal states' initial offsets among the residual move's coordinates."""
    return rm.K * pm.nm + pm.internal


def internal_offsets(
    rm: ResidualMove, pm: particle_model.ParticleModel, path: Float[Array, "T n"]
) -> Float[Array, " k"]:
    """The internal states' initial values of ``path`` as offsets from the initial prior's mean, in
    the residual move's units (the prior's sds): the system move's extra coordinates."""
    internal = pm.internal
    return (path[0, internal] - pm.mech0_mean[internal]) / rm.scale_0[internal]


def system_log_target(
    hyper: Hyper,
    pm: particle_model.ParticleModel,
    rm: ResidualMove,
    od: ObservationDensity,
    tr: particle_model.Transition,
    x_hyper: Float[Array, " p"],
    x_sys: Float[Array, " s"],
    g: Float[Array, "T nl"],
    path: Float[Array, "T n"],
) -> Float[Array, ""]:
    """The move's log target at ``x_sys`` whose model is ``pm`` (transition ``tr``, move ``rm``),
    latent ``g`` and ``path`` (module doc), up to a constant."""
    return (
        hyper.joint_log_prior(jnp.concatenate([x_hyper, x_sys]))
        + latent_log_density(tr, g)
        + observation_log_likelihood(pm, od, path)
        + _log_jacobian(rm, path.shape[0])
    )


def system_move(
    key: Array,
    rwm: mcmc.RWMState,
    hyper: Hyper,
    pm_base: particle_model.ParticleModel,
    rm: ResidualMove,
    od: ObservationDensity,
    x_hyper: Float[Array, " p"],
    tr: particle_model.Transition,
    path: Float[Array, "T n"],
    n_steps: int,
    *,
    adapt: Array,
    reshape_steps: Array,
    step0: Array,
    target: float,
    internal: bool = False,
):
    r"""``n_steps`` residual-preserving Metropolis steps on the system parameters (module doc).

    ``rwm.x``: the chain's system parameters (the joint move's coordinates), ``tr`` the transition
    there at the hyperparameters ``x_hyper``, ``path`` the chain's path; ``pm_base`` the model at
    any system parameters (:meth:`Hyper.model_at` rebuilds it) and ``rm`` its residual move.
    Adapts the walk where ``adapt``, re-shaping it after the steps ``reshape_steps`` (counted from
    ``step0``). Returns ``(rwm, path, tr, accepted)``, the path and transition bit-for-bit the
    input's when nothing was accepted.

    ``internal``: the internal states' initial values are coordinates of the walk too (module doc,
    "The internal states' start"): the returned ``rwm.x`` is the system parameters followed by
    those values' offsets from the initial prior's mean in its sds (:func:`internal_offsets`); the
    ``rwm`` passed in holds the system parameters alone, or both (its offsets are then replaced by
    the path's), its adaptation statistics of both.
    """
    var, ls = hyper.values(x_hyper)
    s = len(hyper.sys_names)
    x_sys0 = rwm.x[:s]
    pm0 = hyper.model_at(pm_base, x_sys0)
    # the held coordinates are the current path's under the current model, extracted once; the
    # builder rebuilds the path under each proposal's model
    build = rm.builder(pm0, od, tr, path, kinematic=True)
    c0 = jnp.zeros(rm.dim)
    if internal:
        idx, a0 = internal_coordinates(rm, pm0), internal_offsets(rm, pm0, path)
        x0 = jnp.concatenate([x_sys0, a0])
    else:
        idx, a0, x0 = None, None, x_sys0
    rwm = rwm._replace(
        x=x0, logdensity=system_log_target(hyper, pm0, rm.at(pm0), od, tr, x_hyper, x_sys0, pm0.latent(path), path)
    )

    def _target(x):
        x_sys = x[:s]
        pm_x = hyper.model_at(pm_base, x_sys)
        tr_x = pm_x.transition(var, ls)
        # the internal states' initial offsets: a translation of held coordinates (module doc)
        c = c0 if idx is None else c0.at[idx].set(x[s:] - a0)
        g, path_x = build(c, at=(pm_x, tr_x))
        return system_log_target(hyper, pm_x, rm.at(pm_x), od, tr_x, x_hyper, x_sys, g, path_x), (path_x, tr_x)

    def _one(carry, s):
        r, aux = carry
        k = jax.random.fold_in(key, s)
        r, info, aux = mh_step(
            k, r, _target, adapt=adapt, reshape=jnp.any(step0 + s == reshape_steps), target=target, aux=aux
        )
        return (r, aux), info.accepted

    (rwm, (path, tr)), accepted = jax.lax.scan(_one, (rwm, (path, tr)), jnp.arange(int(n_steps)))
    return rwm, path, tr, accepted
