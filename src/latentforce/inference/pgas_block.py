r"""One Gibbs block of one PGAS chain: its state, its data and the moves it makes (Algorithm 5, Vibration 2020).

:func:`make_block` builds ``block(state, b, data) -> (state, BlockInfo)``, a pure,
jittable function of the chain's :class:`ChainState`, the block index and the record
(:class:`BlockData`): a PGAS sweep (:mod:`latentforce.inference.smc`) for the trajectory,
the Metropolis-within-Gibbs hyperparameter steps (centred and non-centred), the
low-frequency and residual-preserving trajectory moves, and the running sums of the
post-burn-in states, and (where some sensor's noise level is inferred) one exact
Gibbs update of each inferred noise variance (:mod:`latentforce.inference.noise_gibbs`).
:class:`Schedule` lays out the blocks of a run and
:func:`reshape_chunks` its segments; the driver that vmaps and scans the block is
:func:`latentforce.inference.pgas.run_pgas`.

**Smoother move.** Right after the sweep, ``smoother_steps``
Metropolis-Hastings steps whose proposal is built from the smoother of the model
linearised about the chain's centre path
(:mod:`latentforce.inference.smoother_move`; an independence step, then
Crank-Nicolson steps of decreasing size about it): for a smooth force (Matérn-5/2,
7/2) the sweep's ancestor weights collapse and it hardly renews the path,
while with a displacement channel this move accepts most of its proposals,
each a whole new path, and with acceleration alone its small steps still move
it. Its random numbers come from the chain's key folded with
:data:`~latentforce.inference.smoother_move.SMOOTHER_STREAM`. A state without a
centre (``centre=None``) skips it.

**Joint move.** With free hyperparameters (and a centre), the block starts
with ``joint_steps`` Metropolis-Hastings steps on :math:`(\theta, \text{path})`
together (:func:`~latentforce.inference.smoother_move.joint_move`): a random
walk on :math:`\log\theta` whose path is drawn from the smoother about the
centre at the proposed :math:`\theta`, accepted on the linearised marginal
likelihood corrected by the smoother move's weights. Its walk
(``ChainState.rwm_joint``) adapts like the others in burn-in, re-shaped from
its own running covariance, i.e. the marginal posterior's; random numbers
from :data:`~latentforce.inference.smoother_move.JOINT_STREAM`.

**Low-frequency trajectory move.** With acceleration-only data the weakly
observed direction of the path is a slow, coherent shift of force and
displacement (:math:`\delta u \approx k\,\delta z` leaves the acceleration
unchanged). The ancestor-sampling splice keeps the reference's future latent
and changes only the mechanical state, so the sweep alone cannot move that
component and chains stay where they start. After each sweep
``lowfreq_steps`` Metropolis steps (:func:`lowfreq_move`) therefore move, at
fixed :math:`\theta`, the ``lowfreq_modes`` lowest DCT-II modes (and the
first innovation) of every column of the latent's whitened innovations (the
non-centred coordinates, prior :math:`N(0, I)`), the path being rebuilt by
``colour`` and :meth:`~particle_model.ParticleModel.path`; the proposal's shape is a
Gauss-Newton posterior covariance at the initial path (for nonlinear
systems recomputed at each chain's path at 5, 10, 20, 40, 70 % of the burn-in)
and its scale adapts in burn-in.

**Residual-preserving trajectory move.** On a stiffening system the slow
direction is not a fixed combination of modes: the force follows a slow
displacement offset through the *tangent* stiffness
:math:`k + 3k_3 z(t)^2`, which varies fast, so holding the fast innovations
(the move above) pins it (Duffing, acceleration only: conditional sd of the
mean force a twentieth of the posterior's). After it, ``residual_steps``
Metropolis steps (:func:`residual_move`, :class:`ResidualMove`) move the
slow content of the mechanical within-step noise and rebuild the force
sample by sample so that the acceleration predictions, hence the residuals,
stay as they were; the map has a constant Jacobian, so the acceptance ratio
is exact for any system (prior ratio times the other channels' likelihood
ratio). Gauss-Newton shape, recomputed like the low-frequency move's;
scale adapted in burn-in.

**The internal states' start-up move.** Where the system has internal (hysteretic) states, some
channel sees the force and no system parameter is sampled, after the residual-preserving move
``internal_steps`` Metropolis steps (:func:`latentforce.inference.internal_move.internal_move`)
move their initial values with the displacements, velocities and accelerometer residuals held
(the system move's map at fixed parameters; the force takes up the change); a fixed kernel, no
adaptation; random numbers from :data:`~latentforce.inference.internal_move.INTERNAL_STREAM`.

**The profile move.** Where the start-up move would run (and a centre is carried), then
``profile_steps`` Metropolis-Hastings steps of :func:`latentforce.inference.profile_move.profile_move`:
the internal states' initial values stepped with the whole path re-drawn from the linearised
posterior re-centred at each value (Gauss-Newton with them pinned, from ``state.centre``) and
conditioned on it; accepted on the linearised marginal likelihood, the conditioned Gaussian's
marginal density of the initial values and the smoother move's weight (exact for any system). A
fixed kernel within the block; random numbers from
:data:`~latentforce.inference.profile_move.PROFILE_STREAM`.

**System parameters with the measured motion held.** Where system parameters are sampled
and some channel sees the force, after the path moves ``system_steps`` Metropolis steps
(:func:`latentforce.inference.system_moves.system_move`) move them with the path's
displacements, velocities and accelerometer residuals held, the force taking up the change
of the restoring force: exact (a bijection of constant Jacobian for each parameter value),
no linearisation. Its walk (``ChainState.rwm_sys``) adapts in burn-in; random numbers from
:data:`~latentforce.inference.system_moves.SYSTEM_STREAM`. Where the start-up move would run
(:func:`system_internal`), the walk carries the internal states' initial values too, so that
a parameter and the initial hysteretic force it needs move together.

**Sampling space.** The random walk runs in *log* space,
:math:`x = \log\theta` (this method's choice, overriding the softplus default
of INTERFACE.md; the priors stay on the physical values):

.. math:: \log \pi(x) = \sum_i \left[\log p(\theta_i) + x_i\right]
    + \log N(x_{f,1}; 0, P_{\infty,f}(\theta))
    + \sum_{t=2}^T \log N(x_{f,t}; A_f(\theta) x_{f,t-1}, Q_f(\theta)),

the :math:`x_i` being :math:`\log|d\theta_i/dx_i|`. Why: given a long path
the GP density pins the high-frequency scale of the force (for Matérn-1/2
the quadratic variation gives :math:`q = 2\sigma_f^2/\ell` to a relative
error of about :math:`\sqrt{2/T}`; for Matérn-:math:`\nu`,
:math:`\sigma_f^2/\ell^{2\nu}`) while the direction along that ridge is
only weakly identified. In log space the ridge is a straight line, so a
random walk with a full (adapted) covariance follows it; in softplus space
it is curved, and with :math:`\sigma_f^2 \gg 1` softplus is the identity, a
poor scale for a positive scale parameter.

**Adaptation** (burn-in only, so the post-burn-in chain is a plain
Metropolis-within-Gibbs chain with a fixed proposal and is exact): the
kernel is :func:`latentforce.inference.mcmc.step` (Haario, Saksman &
Tamminen 2001 covariance, Robbins-Monro scale towards
:func:`~latentforce.inference.mcmc.target_acceptance`). The proposal shape is
reset from the chain's covariance at the end of doubling windows of the
burn-in (at 5, 10, 20, 40 and 70 % of its MH steps), the running moments
being restarted after each reset so that the transient from the dispersed
start does not stretch the later proposals.

**Priors** along that ridge: ``docs/nonlinear.md``, "Hyperparameters". **Window move**: on a long
record, one pass after the smoother move (:mod:`latentforce.inference.window_move`; ``window``).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from latentforce.inference import (
    internal_move,
    mcmc,
    noise_gibbs,
    particle_model,
    profile_move,
    smc,
    smoother_move,
    system_moves,
    window_move,
)
from latentforce.inference.hyper_moves import Hyper, adaptation_schedule, mh_step, noncentred_log_target
from latentforce.inference.latent import ObservationDensity, observation_density, observation_log_likelihood, whiten
from latentforce.inference.path_moves import (
    LowFrequencyFrame,
    ResidualMove,
    lowfreq_init,
    lowfreq_move,
    residual_init,
    residual_move,
)
from latentforce.inference.pgas_schedule import Schedule, cut_warm_up, reshape_chunks, schedule  # noqa: F401 (re-exported)
from latentforce.inference.pgas_state import NOT_RUN, BlockData, BlockInfo, ChainState  # noqa: F401 (re-exported)


def _summary_quantities(pm: particle_model.ParticleModel, path: Float[Array, "T n"]):
    return jnp.concatenate([path[:, pm.layout.mech], path[:, pm.layout.force]], axis=1)


def path_move_shapes(
    pm: particle_model.ParticleModel,
    rm: ResidualMove,
    basis,
    od: ObservationDensity,
    tr: particle_model.Transition,
    path: Float[Array, "T n"],
    with_residual: bool,
) -> tuple[mcmc.RWMState, mcmc.RWMState]:
    """Fresh low-frequency and residual-preserving walks shaped at ``path`` (:func:`lowfreq_init`,
    :func:`residual_init`); without the residual move its walk is a copy of the other."""
    lf = lowfreq_init(pm, od, LowFrequencyFrame(tr, basis), path)
    return lf, (residual_init(rm, pm, od, tr, path) if with_residual else lf)


def _with_scale_of(fresh: mcmc.RWMState, adapted: mcmc.RWMState) -> mcmc.RWMState:
    """``fresh``'s shape with ``adapted``'s scale and adaptation count (the re-shaping keeps the scale)."""
    return fresh._replace(log_scale=adapted.log_scale, count=adapted.count)


def system_internal(pm, rm, n_sys: int, system_steps: int, internal_steps: int) -> int:
    """How many internal states' initial values the system move's walk carries besides the
    system parameters (:func:`~latentforce.inference.system_moves.system_move`, ``internal``):
    all of them where system parameters are sampled, the system move runs and so would the
    start-up move (``internal_steps`` positive: ``run_pgas`` sets it to zero where the initial
    prior ties them, :func:`~latentforce.inference.internal_move.free`); else none."""
    on = n_sys and int(system_steps) > 0 and rm.applies and int(internal_steps) > 0 and internal_move.applies(pm, rm)
    return pm.nm - 2 * pm.ndof if on else 0


def make_block(
    pm: particle_model.ParticleModel,
    hyper: Hyper,
    sched: Schedule,
    rm: ResidualMove,
    basis,
    tpoints,
    mpoints,
    *,
    particles: int = 50,
    proposal: str = "optimal",
    resampling: str = "multinomial",
    ancestor_sampling: bool = True,
    unroll: int = 1,
    interweave: bool = True,
    lowfreq_steps: int = 5,
    residual_steps: int,
    smoother_steps: int = 1,
    window: int = 0,
    joint_steps: int = 1,
    system_steps: int = 0,
    internal_steps: int = 0,
    profile_steps: int = 0,
    recentre: int = smoother_move.JOINT_RECENTRE,
    noise: noise_gibbs.NoiseLevels = noise_gibbs.NoiseLevels(),
) -> Callable:
    r"""``block(state, b, data) -> (state, BlockInfo)``: Gibbs block ``b`` of one chain (pure, jittable).

    :func:`~latentforce.inference.pgas.run_pgas` calls this inside its compiled
    chunk, with ``pm``, ``hyper``, ``rm``, ``basis`` and ``noise`` traced (pytrees
    whose leaves are the numbers), so the closure is rebuilt at each trace and
    the compiled program serves every run of one structure.

    A PGAS sweep at the carried transition; ``smoother_steps`` smoother moves
    about ``state.centre`` (module doc); ``lowfreq_steps`` low-frequency
    moves (``basis``: :func:`lowfreq_basis`) and ``residual_steps``
    residual-preserving moves (``rm``; skipped where it does not apply; no default: the
    caller chooses, :func:`~latentforce.inference.pgas_defaults.default_residual_steps` for run_pgas); the
    post-burn-in running sums and thinned draws; then ``state_every``
    Metropolis-within-Gibbs iterations of ``mh_steps`` centred and (with
    ``interweave``) non-centred steps on :math:`\theta`. Blocks
    ``b < sched.burn_blocks`` adapt the proposals' scales; later blocks are a
    fixed kernel. The path moves' shapes are the caller's (for nonlinear
    systems :func:`~latentforce.inference.pgas.run_pgas` re-computes them between burn-in blocks with
    :func:`path_move_shapes`). ``b`` must be shared by vmapped chains (it drives conditionals);
    ``data`` (:class:`BlockData`) may be shared or batched. ``tpoints``: the
    time indices whose force values are recorded.

    System parameters (``hyper.sys_names``) are moved by the joint move, which then must
    run (``joint_steps`` and ``smoother_steps`` positive, the state holding ``centre`` and
    ``rwm_joint``), and by ``system_steps`` steps of the system move with the measured motion
    held (module doc; the state holding ``rwm_sys``; skipped where no channel sees the force);
    the chain's values are ``rwm_joint.x[p:]`` (log space), and every other
    move of the block runs on the model at them (:meth:`~latentforce.inference.hyper_moves.Hyper.model_at`).

    The caller's :class:`ChainState` must hold ``tr``, the transition at
    ``rwm.x`` (and at the system parameters), and ``draws`` with ``sched.n_draws + 1`` slots (the last is a
    discard slot); ``data.ref_q`` centres the running sums (``(T, q)``, see
    :func:`~latentforce.inference.pgas.run_pgas`). The walks' ``logdensity`` fields are refreshed before
    use. ``mpoints``: the time indices whose displacement, velocity and force are
    recorded every block (the convergence monitor). The stored-draw stride is the
    state's ``thin`` (``sched.thin`` at the start).

    ``noise`` (:class:`~latentforce.inference.noise_gibbs.NoiseLevels`): the
    channels whose noise level is inferred. With any, the block's noise
    covariance is ``diag(state.noise_var)`` (the chain's own, which the state
    must then hold) wherever ``data.od`` (and its ``R``) would be used, and
    after the hyperparameter steps each inferred variance gets one exact Gibbs
    update given the final path (:func:`~latentforce.inference.noise_gibbs.gibbs_step`),
    its random numbers from the chain's key folded with
    :data:`~latentforce.inference.noise_gibbs.NOISE_STREAM` (a run without
    inferred noise draws what it drew before).
    """
    p, n_sys = len(hyper.names), len(hyper.sys_names)
    k_every, n_mh, burn_in = sched.state_every, sched.mh_steps, sched.burn_in
    n_blocks, burn_blocks, n_draws = sched.n_blocks, sched.burn_blocks, sched.n_draws

    def make_sweep(pm_):
        return smc.make_sweep(
            pm_,
            particles,
            proposal=proposal,
            resampling=resampling,
            conditional=True,
            ancestor_sampling=ancestor_sampling,
            unroll=unroll,
        )

    pm_base, rm_base = pm, rm  # the block's own pm and rm: the chain's, at its system parameters
    sweep_fixed = make_sweep(pm)
    target_acc = mcmc.target_acceptance(max(p, 1))
    target_joint = mcmc.target_acceptance(max(p + n_sys, 1))
    reshape_steps = jnp.asarray(adaptation_schedule(burn_in * n_mh) or (-1,))
    n_lf, n_rp = int(lowfreq_steps), int(residual_steps)
    if n_lf < 0:
        raise ValueError(f"lowfreq_steps must be non-negative, got {lowfreq_steps}")
    if n_rp < 0:
        raise ValueError(f"residual_steps must be non-negative, got {residual_steps}")
    n_rp = n_rp if rm.applies else 0
    n_sm = int(smoother_steps)
    if n_sm < 0:
        raise ValueError(f"smoother_steps must be non-negative, got {smoother_steps}")

    n_win = int(window)
    if n_win < 0:
        raise ValueError(f"the window width must be non-negative, got {window}")
    n_joint = int(joint_steps)
    if n_joint < 0:
        raise ValueError(f"joint_steps must be non-negative, got {joint_steps}")
    # re-centred joint moves (smoother_move.JOINT_RECENTRE) where system parameters of a hysteretic
    # system are sampled: on the Bouc-Wen benchmark with gamma sampled, 600 iterations, 4 chains,
    # gamma's bulk ESS 27 -> 173 for 1.2-1.5x the time; on the Duffing demo with c, k3 sampled it
    # cost 25 % more time for no gain in ESS, so there the expansion keeps its fixed centre
    joint_recentre = int(recentre) if n_sys and not pm_base.is_linear and pm_base.model.system.n_internal else 0
    joint_reshape = jnp.asarray(adaptation_schedule(sched.burn_blocks * n_joint) or (-1,))
    if n_sys and not (n_joint and n_sm):
        raise ValueError(
            f"system parameters {hyper.sys_names} are sampled by the joint move only: "
            f"joint_steps and smoother_steps must be positive, got {joint_steps} and {smoother_steps}"
        )

    # the system parameters' move with the measured motion held (system_moves): where they are
    # sampled and some channel sees the force
    if int(system_steps) < 0:
        raise ValueError(f"system_steps must be non-negative, got {system_steps}")
    n_sysrp = int(system_steps) if n_sys and rm.applies else 0
    sys_reshape = jnp.asarray(adaptation_schedule(sched.burn_blocks * n_sysrp) or (-1,))
    # its walk is on the internal states' initial values too where the start-up move would run
    # (system_moves, "The internal states' start")
    n_sys_int = system_internal(pm, rm, n_sys, system_steps, internal_steps)
    target_sys = mcmc.target_acceptance(max(n_sys + n_sys_int, 1))
    # the internal states' start-up move (internal_move): where the system has internal states and
    # no system parameter is sampled; where some are, the system move's walk carries the internal
    # states' initial values (system_internal), so that a parameter and the initial hysteretic
    # force it needs move together (docs/nonlinear.md: 1.4-2.6x sooner to converged on the
    # Bouc-Wen gamma record than with neither)
    if int(internal_steps) < 0:
        raise ValueError(f"internal_steps must be non-negative, got {internal_steps}")
    n_int = int(internal_steps) if internal_move.applies(pm_base, rm) and not n_sys else 0
    # the profile move (profile_move): the internal states' initial values with the path re-drawn
    # about a Gaussian re-centred at each; where no system parameter is sampled, about the centre
    if int(profile_steps) < 0:
        raise ValueError(f"profile_steps must be non-negative, got {profile_steps}")
    n_prof = int(profile_steps) if profile_move.applies(pm_base) and not n_sys else 0

    lf_reshape = jnp.asarray((-1,))
    n_noise = len(noise.channels)
    interweave = bool(interweave) and p > 0

    def _block(state: ChainState, b, data: BlockData):
        """One Gibbs block of one chain (:func:`make_block`)."""
        key, k_sweep, k_mh, k_lf, k_rp = jax.random.split(state.key, 5)
        tr = state.tr
        if n_noise:  # the chain's own noise levels
            od = observation_density(pm_base, data.y, data.mask, jnp.diag(state.noise_var))
        else:
            od = data.od
        not_run = jnp.full((), NOT_RUN)  # a move's acceptance until it runs
        reference, rwm_x, rwm_joint, acc_joint = state.reference, state.rwm.x, state.rwm_joint, not_run
        if n_joint and (p or n_sys) and state.centre is not None and rwm_joint is not None:
            k_joint = jax.random.fold_in(state.key, smoother_move.JOINT_STREAM)
            # the joint walk's x: the hyperparameters (kept in rwm.x), then the system parameters
            rwm_joint, reference, tr, accs_joint = smoother_move.joint_move(
                k_joint,
                rwm_joint._replace(x=jnp.concatenate([state.rwm.x, rwm_joint.x[p:]])),
                pm_base,
                hyper,
                od,
                state.centre,
                state.tr,
                state.reference,
                n_joint,
                adapt=b < burn_blocks,
                reshape_steps=joint_reshape,
                step0=b * n_joint,
                target=target_joint,
                recentre=joint_recentre,
            )
            rwm_x, acc_joint = rwm_joint.x[:p], jnp.mean(accs_joint.astype(float))
        # the chain's model at its system parameters (the block's moves below hold them fixed)
        x_sys = rwm_joint.x[p:] if n_sys else jnp.zeros(0)
        pm = hyper.model_at(pm_base, x_sys)
        rm = rm_base.at(pm) if n_sys else rm_base
        sweep = make_sweep(pm) if n_sys else sweep_fixed
        sc = smc.sweep_constants(pm, tr, data.y, data.mask, proposal, od.R)
        out = sweep(k_sweep, sc, reference)
        path = out.trajectory
        acc_sm = not_run
        if n_sm and state.centre is not None:
            # its own stream (folded in): a run without the move draws what it drew before
            k_sm = jax.random.fold_in(state.key, smoother_move.SMOOTHER_STREAM)
            path, accs_sm = smoother_move.smoother_move(k_sm, pm, tr, od, state.centre, path, n_sm)
            acc_sm = jnp.mean(accs_sm.astype(float))
        acc_win = not_run
        if n_win and state.centre is not None:
            k_win = jax.random.fold_in(state.key, window_move.WINDOW_STREAM)
            path, accs_win = window_move.window_move(k_win, pm, tr, od, state.centre, path, n_win)
            acc_win = jnp.mean(accs_win.astype(float))
        rwm_lf, acc_lf = state.rwm_lf, not_run
        if n_lf:
            frame = LowFrequencyFrame(tr, basis)
            rwm_lf, path, accs_lf = lowfreq_move(
                k_lf, rwm_lf, pm, od, frame, path, n_lf, adapt=b < burn_blocks, step0=b * n_lf, reshape_steps=lf_reshape
            )
            acc_lf = jnp.mean(accs_lf.astype(float))
        rwm_rp, acc_rp = state.rwm_rp, not_run
        if n_rp:
            rwm_rp, path, accs_rp = residual_move(k_rp, rwm_rp, rm, pm, od, tr, path, n_rp, adapt=b < burn_blocks)
            acc_rp = jnp.mean(accs_rp.astype(float))
        acc_int = not_run
        if n_int:
            k_int = jax.random.fold_in(state.key, internal_move.INTERNAL_STREAM)
            path, accs_int = internal_move.internal_move(k_int, rm, pm, od, tr, path, n_int)
            acc_int = jnp.mean(accs_int.astype(float))
        acc_prof = not_run
        if n_prof and state.centre is not None:
            k_prof = jax.random.fold_in(state.key, profile_move.PROFILE_STREAM)
            path, accs_prof = profile_move.profile_move(k_prof, pm, tr, od, state.centre, path, n_prof)
            acc_prof = jnp.mean(accs_prof.astype(float))
        rwm_sys, acc_sys = state.rwm_sys, not_run
        if n_sysrp and rwm_sys is not None:
            rwm_sys, path, tr, accs_sys = system_moves.system_move(
                jax.random.fold_in(state.key, system_moves.SYSTEM_STREAM),
                rwm_sys._replace(x=x_sys),
                hyper,
                pm_base,
                rm_base,
                od,
                rwm_x,
                tr,
                path,
                n_sysrp,
                adapt=b < burn_blocks,
                reshape_steps=sys_reshape,
                step0=b * n_sysrp,
                target=target_sys,
                internal=bool(n_sys_int),
            )
            acc_sys = jnp.mean(accs_sys.astype(float))
            # the block's other moves go on at the chain's new system parameters
            x_sys = rwm_sys.x[:n_sys]
            rwm_joint = rwm_joint._replace(x=jnp.concatenate([rwm_joint.x[:p], x_sys]))
            pm = hyper.model_at(pm_base, x_sys)
        # ---- accumulate post-burn-in state samples
        post = (b >= burn_blocks) & (b < n_blocks)
        wgt = post.astype(float)
        q = _summary_quantities(pm, path) - data.ref_q
        sum1 = state.sum1 + wgt * q
        sum2 = state.sum2 + wgt * q**2
        sidx = b - burn_blocks
        slot = jnp.where(post & (sidx % state.thin == 0), sidx // state.thin, n_draws)
        draws = state.draws.at[slot].set(path)

        # ---- state_every MH iterations given the path, each mh_steps steps
        def _steps(key_, r, target, j, aux=None):
            def _one(carry, inp2):
                r_, a_ = carry
                kk, s_ = inp2
                out_ = mh_step(
                    kk,
                    r_,
                    target,
                    adapt=j < burn_in,
                    reshape=jnp.any(j * n_mh + s_ == reshape_steps),
                    target=target_acc,
                    aux=a_,
                )
                return (out_[0], out_[2] if aux is not None else None), out_[1].accepted

            (r, aux), accs_ = jax.lax.scan(_one, (r, aux), (jax.random.split(key_, n_mh), jnp.arange(n_mh)))
            return r, accs_, aux

        def _mh_iter(carry, inp):
            rwm, rwm_nc, path_, g_, tr_ = carry
            k_it, j = inp
            if not p:
                return carry, (rwm.x, jnp.zeros(()), jnp.zeros(()))
            k_c, k_nc = jax.random.split(k_it)

            def centred(x):
                return hyper.log_target_and_transition(pm, x, g_)

            # the conditioning path may have changed: refresh the current point's target
            rwm = rwm._replace(logdensity=hyper.log_target_given(tr_, rwm.x, g_))
            rwm, accs, tr_ = _steps(k_c, rwm, centred, j, aux=tr_)
            acc_nc = jnp.zeros(())
            if interweave:
                eps = whiten(tr_, g_)

                def noncentred(x):
                    return noncentred_log_target(hyper, pm, od, x, eps)

                # at the current point the rebuilt path is the current one (up to round-off);
                # the path is kept bit-for-bit when nothing moves (no round-off drift)
                rwm_nc = rwm_nc._replace(
                    x=rwm.x, logdensity=hyper.log_prior(rwm.x) + observation_log_likelihood(pm, od, path_)
                )
                rwm_nc, accs_nc, (g_, path_, tr_) = _steps(k_nc, rwm_nc, noncentred, j, aux=(g_, path_, tr_))
                rwm = rwm._replace(x=rwm_nc.x)
                acc_nc = jnp.mean(accs_nc.astype(float))
            return (rwm, rwm_nc, path_, g_, tr_), (rwm.x, jnp.mean(accs.astype(float)), acc_nc)

        js = b * k_every + jnp.arange(k_every)
        (rwm, rwm_nc, path_end, _, tr_end), (xs, accs, accs_nc) = jax.lax.scan(
            _mh_iter,
            (state.rwm._replace(x=rwm_x), state.rwm_nc, path, pm.latent(path), tr),
            (jax.random.split(k_mh, k_every), js),
        )
        theta = hyper.to_constrained(xs)
        fp = path[tpoints][:, pm.layout.force]
        # ---- the inferred noise levels given the final path (one exact Gibbs update each)
        noise_var, sds, acc_noise = state.noise_var, jnp.zeros((k_every, 0)), jnp.zeros(0)
        if n_noise:
            k_noise = jax.random.fold_in(state.key, noise_gibbs.NOISE_STREAM)
            noise_var, acc_noise = noise_gibbs.gibbs_step(k_noise, noise, pm, od, path_end, state.noise_var)
            old, now = (noise_gibbs.standard_deviations(noise, v) for v in (state.noise_var, noise_var))
            sds = jnp.where((jnp.arange(k_every) == k_every - 1)[:, None], now, old)
            acc_noise = acc_noise.astype(float)
        new = ChainState(
            key,
            path_end,
            rwm,
            rwm_nc,
            rwm_lf,
            rwm_rp,
            tr_end,
            b + 1,
            sum1,
            sum2,
            state.count + wgt,
            draws,
            state.thin,
            noise_var,
            state.centre,
            rwm_joint,
            rwm_sys,
        )
        info = BlockInfo(
            theta,
            accs,
            accs_nc,
            acc_lf,
            acc_rp,
            out.info.log_likelihood,
            out.info.switched,
            jnp.mean(out.info.ess),
            fp,
            _summary_quantities(pm, path)[mpoints],
            sds,
            acc_noise,
            acc_sm,
            acc_joint,
            jnp.broadcast_to(hyper.system_array(x_sys), (k_every, n_sys)),
            acc_sys,
            acc_int,
            acc_win,
            acc_prof,
        )
        return new, info

    return _block
