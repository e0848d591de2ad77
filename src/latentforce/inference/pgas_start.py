r"""Where the particle Gibbs chains start: the extended Kalman smoother of the sampler's model,
over-dispersed starts around the Gauss-Newton path from its mean (:func:`dispersed_start`), and
every chain's first state (:func:`init_chains`)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from latentforce.compile import jit
from latentforce.inference import mcmc, noise_gibbs, particle_model
from latentforce.inference.hyper_moves import init_proposal
from latentforce.inference.kalman import _update
from latentforce.inference.latent import ObservationDensity
from latentforce.inference.path_moves import (
    LowFrequencyFrame,
    lowfreq_coordinates,
    lowfreq_log_target,
    lowfreq_path,
)
from latentforce.inference.pgas_block import ChainState
from latentforce.linalg import cholesky, solve, symmetrise


def extended_kalman_smoother(
    pm: particle_model.ParticleModel, tr: particle_model.Transition, y, mask, R=None
) -> Float[Array, "T n"]:
    r"""Smoothed means of the sampler's state-space model in ``(mech, x_f)``.

    The transition is :math:`x_t = (\Phi(\mathrm{mech}_{t-1}, x_{f,t-1}) + E x_{f,t-1},
    A_f x_{f,t-1}) + q_t` with the latent's joint noise :math:`q_t`
    (:meth:`~particle_model.ParticleModel.linear_discrete`). Extended Kalman filter
    (Jacobians by ``jax.jacfwd``) with the Kalman update of
    :mod:`latentforce.inference.kalman` applied to the linearised
    observation, then an RTS pass with the per-step Jacobians (Särkkä 2013,
    Alg. 9.5). Exact for linear systems. ``R``: the channels' noise covariance
    (default ``pm.R``).
    """
    R = pm.R if R is None else R
    y = jnp.asarray(y, dtype=float)
    mask = jnp.asarray(mask, dtype=bool)
    _, Qd, _, m0, P0 = pm.linear_discrete(tr)

    def f(x):
        return pm.state_step(tr, x)

    h = pm.readout

    def _filter(carry, inputs):
        m, P = carry
        y_t, mask_t = inputs
        H = jax.jacfwd(h)(m)
        # the linear update with y shifted so that the innovation is y - h(m)
        y_lin = jnp.where(mask_t, y_t, 0.0) - h(m) + H @ m
        m_f, P_f, _ = _update(m, P, H, R, y_lin, mask_t)
        F = jax.jacfwd(f)(m_f)
        m_p = f(m_f)
        P_p = symmetrise(F @ P_f @ F.T + Qd)
        return (m_p, P_p), (m_f, P_f, m_p, P_p, F)

    _, (ms, Ps, mps, Pps, Fs) = jax.lax.scan(_filter, (m0, P0), (y, mask))

    def _smooth(carry, inputs):
        m_next, P_next = carry
        m_f, P_f, m_p, P_p, F = inputs
        G = solve(P_p + 1e-12 * jnp.diag(jnp.diagonal(P_p)), F @ P_f).T
        m_s = m_f + G @ (m_next - m_p)
        P_s = symmetrise(P_f + G @ (P_next - P_p) @ G.T)
        return (m_s, P_s), m_s

    _, msm = jax.lax.scan(_smooth, (ms[-1], Ps[-1]), (ms[:-1], Ps[:-1], mps[:-1], Pps[:-1], Fs[:-1]), reverse=True)
    return jnp.concatenate([msm, ms[-1:]])


def dispersal_cov(cov: Float[Array, "q q"], spread: float) -> Float[Array, "q q"]:
    r"""The covariance of a chain's start about its base path in the low-frequency coordinates:
    the linearised posterior with the data's information divided by ``spread``\ :sup:`2`,

    .. math:: S = \big(I + (C^{-1} - I)/s^2\big)^{-1},

    ``cov`` :math:`C = (I + J^\top R^{-1} J)^{-1}` the Gauss-Newton posterior covariance of the
    coordinates, whose prior is :math:`N(0, I)` (:func:`~latentforce.inference.path_moves.lowfreq_init`).
    A direction the data pin (precision :math:`h \gg 1`) is dispersed by ``spread`` posterior sds, as
    :math:`s^2 C` did; one the linearisation leaves to the prior by at most one prior sd, never
    :math:`s` of them. Measured on the 3-storey frame with a Bouc-Wen brace (accelerations at
    floors 0 and 2, hyperparameters at the truth, one run each, 240 s), from the Gauss-Newton path
    (:func:`dispersed_start`): at Matérn-1/2 :math:`s^2 C` gave R-hat 1.022 (bulk ESS 239) and this
    dispersal 1.009 (ESS 498); at 3/2 the two coincided (1.008, ESS 640: the data pin every
    direction there).
    """
    # = s^2 C (I + (s^2 - 1) C)^-1: no inverse of C (its eigenvalues span orders of magnitude), and
    # I + (s^2 - 1) C has its eigenvalues in [1, s^2]
    s2 = float(spread) ** 2
    return symmetrise(s2 * solve(jnp.eye(cov.shape[0]) + (s2 - 1.0) * cov, cov))


#: halvings of a chain's starting step tried where the full step lands too far down the posterior
#: (:func:`dispersed_start`)
START_HALVINGS = 8


def dispersed_start(
    key: Array,
    pm: particle_model.ParticleModel,
    frame: LowFrequencyFrame,
    rwm_lf: mcmc.RWMState,
    path: Float[Array, "T n"],
    od: ObservationDensity,
    spread: float = 2.0,
) -> Float[Array, "T n"]:
    r"""A chain's starting path: ``path`` (Gauss-Newton's, a path of the model) moved in the
    low-frequency coordinates by a draw of :func:`dispersal_cov` of their Gauss-Newton posterior
    covariance (``rwm_lf.cov``, :func:`lowfreq_init`): ``spread`` posterior sds where the data pin a
    direction, at most a prior sd where they do not.

    Over-dispersed exactly where the sampler is slow (the weakly observed, slow
    directions), while every acceleration sample stays fitted; the first sweep
    disperses the observed, fast content. Adding prior-scale noise to the whole
    latent path instead (the earlier start) leaves the mechanical path out of
    step with the force: on the Duffing case each acceleration sample was missed
    by about the force perturbation (log-likelihood near -1e6 against +2300 at
    the posterior), and the conditional SMC needed tens of sweeps to climb back,
    longer than a quick run's burn-in.

    The covariance is the linearisation's; where the system's nonlinearity pins a direction the
    linearisation leaves to the prior (a Duffing record's initial displacement), a draw's fit can
    fall far (600 nats of log-likelihood on the acceleration-only Duffing test record; with a
    data-blind shape, 2e5-4e6 nats of log target). A step whose log
    target (:func:`~latentforce.inference.path_moves.lowfreq_log_target`) falls more than
    :math:`4q` below the base path's (:math:`q` coordinates; a Gaussian posterior's draw of this
    dispersal falls by at most :math:`2q` on average, sd at most :math:`\sqrt{8q}`) is halved until
    it does not, at most :data:`START_HALVINGS` times.
    """
    w, eps_perp = lowfreq_coordinates(pm, frame, path)
    step = cholesky(dispersal_cov(rwm_lf.cov, spread)) @ jax.random.normal(key, w.shape)
    scales = 0.5 ** jnp.arange(START_HALVINGS + 1.0)
    base = lowfreq_log_target(pm, od, frame, eps_perp, w)[0]
    drops = base - jax.vmap(lambda a: lowfreq_log_target(pm, od, frame, eps_perp, w + a * step)[0])(scales)
    ok = drops <= 4.0 * w.shape[0]  # NaN (a path that blew up) is never ok
    scale = jnp.where(jnp.any(ok), scales[jnp.argmax(ok)], 0.0)
    return lowfreq_path(pm, frame, eps_perp, w + scale * step)


@functools.partial(jit, static_argnames=("chains", "sched"))
def init_chains(
    pm,
    hyper,
    noise,
    basis,
    k_chains,
    tr0,
    start,
    xs0,
    trs0,
    lfs,
    rps,
    R,
    od,
    centres,
    joint_chol,
    int_var,
    *,
    chains,
    sched,
):
    """Every chain's first :class:`ChainState`, from its start path (``start``, leading axis the
    chains: :func:`~latentforce.inference.pgas.run_pgas`) moved by its own dispersion
    (:func:`dispersed_start`) on its own model (system parameters ``xs0[:, p:]``); ``joint_chol``
    the joint walk's first proposal shape;
    ``int_var`` the first guess of the variances of the internal states' offsets that the system
    move's walk carries besides the parameters (none: empty)."""
    frame0 = LowFrequencyFrame(tr0, basis)
    T, nq = start.shape[1], pm.layout.n_mech + pm.nforce  # displacement, velocity, force columns
    # every chain starts from the configured (initial) noise levels; None: none inferred
    var0 = noise_gibbs.initial_variances(noise, R) if noise.channels else None

    def _init_chain(ck, x, tr, lf, rp, centre, start_c):
        k_path, k_run = jax.random.split(ck)
        # with system parameters sampled, on the chain's own model (run_pgas: its start is a path of it)
        p_ = len(hyper.names)
        pm_c, frame = (hyper.model_at(pm, x[p_:]), LowFrequencyFrame(tr, basis)) if hyper.sys_names else (pm, frame0)
        ref = dispersed_start(k_path, pm_c, frame, lf, start_c, od)
        # the log density is set at the first block
        rwm = init_proposal(hyper, lambda x_: jnp.zeros(()), x[: len(hyper.names)])
        joint = init_proposal(hyper, lambda x_: jnp.zeros(()), x)
        # the first proposal's covariance, 2.38^2/d times the guess of the posterior's (a Laplace
        # fit where system parameters are inferred): the guess stays in every reshape (mcmc)
        joint_cov = joint_chol @ joint_chol.T
        joint = joint._replace(chol=joint_chol, cov=joint_cov, cov0=joint_cov * (x.shape[0] / 2.38**2))
        # the system move's walk (system_moves): the same guess's block
        p, s = len(hyper.names), len(hyper.sys_names)
        cov_s = jax.scipy.linalg.block_diag(joint_cov[p:, p:] * (x.shape[0] / 2.38**2), jnp.diag(int_var))
        d_s = s + int_var.shape[0]
        chol_s = cholesky(cov_s) * (2.38 / max(d_s, 1) ** 0.5) if s else jnp.zeros((0, 0))
        x_s = jnp.concatenate([x[p:], jnp.zeros(int_var.shape[0])])  # the offsets: the path's, at each move
        sys_walk = joint._replace(x=x_s, log_scale=jnp.zeros(()), chol=chol_s, mean=x_s, cov=cov_s, cov0=cov_s)
        return ChainState(
            k_run,
            ref,
            rwm,
            rwm,
            lf,
            rp,
            tr,
            jnp.zeros((), jnp.int32),
            jnp.zeros((T, nq)),
            jnp.zeros((T, nq)),
            jnp.zeros(()),
            jnp.zeros((sched.n_draws + 1, T, pm.n_state)),
            jnp.asarray(sched.thin, jnp.int32),
            var0,
            centre,
            joint if hyper.joint_names and centre is not None else None,
            sys_walk if hyper.sys_names and centre is not None else None,
        )

    return jax.vmap(_init_chain)(jax.random.split(k_chains, chains), xs0, trs0, lfs, rps, centres, start)


@functools.partial(jit, static_argnames=("chains",))
def _start_transitions(k, x0, spread, pm, hyper, *, chains):
    """The chains' dispersed starts x_0 + spread eps in the joint coordinates (theta_0 exp(0.5 eps)
    by default; about the filter's mode where system parameters are sampled, pgas_mode), and the
    transitions at x_0 and at those, from one place in the program (each place compiles its own
    matrix exponentials: they dominated the compile time)."""
    p = len(hyper.names)
    xs = x0 + jax.random.normal(k, (chains, len(hyper.joint_names))) @ spread.T
    trs = jax.vmap(lambda x: hyper.model_at(pm, x[p:]).transition(*hyper.values(x)))(jnp.concatenate([x0[None], xs]))
    return xs, jax.tree_util.tree_map(lambda a: a[0], trs), jax.tree_util.tree_map(lambda a: a[1:], trs)
