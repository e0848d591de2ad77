r"""Blocked particle Gibbs for joint input-state-hyperparameter estimation (Algorithm 5, Vibration 2020).

Each Gibbs block is one PGAS sweep (:mod:`latentforce.inference.smc`) for the
trajectory :math:`x_{1:T}` given :math:`\theta` (with the smoother,
low-frequency and residual-preserving path moves after it), then ``state_every``
iterations of Metropolis-within-Gibbs for the GP hyperparameters
:math:`\theta \subseteq \{\sigma_f^2, \ell\}` given the trajectory
(Eq. 23-25), each of ``mh_steps`` random-walk steps. Because the mechanical
map :math:`\Phi` does not depend on :math:`\theta`, the observation terms of
Eq. (25) cancel and the MH target is the density of the latent path
:math:`g = (x_f, w)` (force states and within-step mechanical noise,
:mod:`smc`) times the prior.

The moves of a Gibbs block (the low-frequency and residual-preserving
trajectory moves, the hyperparameters' log-space random walk, its adaptation
and the priors it needs) are derived in :mod:`latentforce.inference.pgas_block`;
what a run returns and its convergence verdict are
:mod:`latentforce.inference.pgas_output`'s.

One Gibbs block of one chain is :func:`make_block` (a pure function of the chain
state, the block index and the data); :func:`run_pgas` initialises the chains,
``jax.vmap``-s the block over them and runs the blocks in a ``lax.scan``; Python only
chunks the scan for progress reports. Initialisation never uses the truth:
an extended Kalman smoother at the initial :math:`\theta` gives a mean that
fits the data, and Gauss-Newton from it a path of the model that does (for a
nonlinear system the smoother's mean is none: its whitened mechanical
innovations reached 3e4 sds); each chain starts from that path moved in the
low-frequency coordinates by a draw of their Gauss-Newton posterior with the
data's information quartered (:func:`~latentforce.inference.pgas_start.dispersed_start`: twice the posterior sd
where the data pin a direction, at most a prior sd where they do not; different
per chain), and from :math:`\theta_0 \exp(0.5\,\varepsilon)` per parameter.

Any key implementation works. The sweep draws its random numbers in two
large batches of 32-bit words before its sequential loop
(:func:`smc.box_muller`, :func:`smc.uniform32`); with jaxlib 0.10 on a
2-core CPU a sweep timed the same with ``threefry2x32``, ``rbg`` and
``unsafe_rbg`` keys (about 10 ns a word for each generator). Under ``vmap``
JAX draws the bits of ``rbg`` keys from the first key of the batch only
(each chain gets its own slice of that one stream, so the chains stay
independent, but a chain's draws then depend on the first chain's key).
"""

from __future__ import annotations

import functools
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from latentforce.compile import jit
from latentforce.inference import (
    convergence,
    internal_move,
    noise_gibbs,
    particle_model,
    pgas_mode,
    profile_move,
    smoother_move,
)
from latentforce.inference.hyper_moves import Hyper
from latentforce.inference.latent import observation_density
from latentforce.inference.path_moves import ResidualMove, lowfreq_basis
from latentforce.inference.pgas_block import (  # noqa: F401 (re-exported: callers use pgas.make_block ...)
    BlockData,
    BlockInfo,
    ChainState,
    Schedule,
    _summary_quantities,
    _with_scale_of,
    cut_warm_up,
    make_block,
    path_move_shapes,
    reshape_chunks,
    schedule,
    system_internal,
)
from latentforce.inference.pgas_channels import _unnamed, observe_through  # noqa: F401 (re-exported)
from latentforce.inference.pgas_defaults import (  # noqa: F401 (re-exported)
    default_particles,
    default_residual_steps,
    default_smoother_steps,
    default_window,
)
from latentforce.inference.pgas_output import PGASOutput, _assemble, _verdict, convergence_diagnostics  # noqa: F401 (re-exported)
from latentforce.inference.pgas_schedule import first_check
from latentforce.inference.pgas_start import _start_transitions, extended_kalman_smoother, init_chains
from latentforce.inference.resume import pgas_loop_state, pgas_restore
from latentforce.models import hyper_names


def run_pgas(
    key: Array,
    model,
    params: dict,
    free: dict,
    y,
    mask,
    dt: float,
    *,
    particles: int | None = None,
    iterations: int | None = 1000,
    burn_in: int = 500,
    state_every: int = 1,
    chains: int = 4,
    mh_steps: int = 1,
    discretisation: str = "rk4",
    proposal: str = "optimal",
    resampling: str = "multinomial",
    thin_draws: int = 200,
    initial=None,
    progress: Callable | None = None,
    chunk_blocks: int = 1000,
    unroll: int = 1,
    time_points: int = 5,
    ancestor_sampling: bool = True,
    interweave: bool = True,
    lowfreq_modes: int = 16,
    lowfreq_steps: int = 5,
    residual_modes: int = 16,
    residual_steps: int | None = None,
    smoother_steps: int | None = None,
    window: int | None = None,
    joint_steps: int = 3,
    system_steps: int = 5,
    internal_steps: int = 10,
    profile_steps: int | None = None,
    joint_recentre: int = smoother_move.JOINT_RECENTRE,
    channels=None,
    target_ess: float = 400.0,
    max_time: float = 600.0,
    max_iterations: int = 50_000,
    checkpoint=None,
) -> PGASOutput:
    r"""Blocked particle Gibbs (Algorithm 5, Vibration 2020) with the PGAS kernel of :mod:`smc`.

    ``params``: every model parameter (free hyperparameters too: their values
    are ignored except as fixed defaults). ``free``: ``name -> (prior, init)``
    for a subset of ``force_variance, force_lengthscale`` (may be empty: the
    trajectory is then sampled at fixed :math:`\theta`), of the system's parameters
    (``model.system.param_names``: m, c, k, k3 ..., moved by the joint move and by ``system_steps``
    steps with the measured motion held (:mod:`~latentforce.inference.system_moves`), each chain's
    other moves on the model at its own values; ``smoother_steps`` and ``joint_steps`` must then
    be positive; recorded like the hyperparameters, after them) and of the sensors'
    noise levels, named by their :attr:`~latentforce.models.Sensor.noise_param`
    (``noise_std_<column>``; the prior on the standard deviation in the
    parameter's unit, the sensor's ``noise_scale`` taking it to SI): each gets
    one exact Gibbs update per block given the path
    (:mod:`latentforce.inference.noise_gibbs`; its channel needs more than two
    observed samples) and is recorded per iteration like the hyperparameters,
    in ``theta`` and the convergence verdicts. ``y`` ``(T, d)`` may
    hold NaN where ``mask`` is False. ``iterations`` are kept after
    ``burn_in``; a PGAS sweep runs on iterations ``j % state_every == 0``,
    and every iteration makes ``mh_steps`` Metropolis steps on
    :math:`\theta` given the current path (the value recorded for the
    iteration is the last); with ``interweave`` each iteration then makes
    ``mh_steps`` non-centred steps (module doc). After each sweep,
    ``lowfreq_steps`` Metropolis steps (:func:`lowfreq_move`; 0 disables)
    move the path's ``lowfreq_modes`` slowest innovation modes and its
    initial mechanical state at fixed :math:`\theta`; the moved path is the
    next reference and the recorded sample. Then ``residual_steps``
    residual-preserving steps (:func:`residual_move`; 0 disables; skipped
    when no channel sees the force; None:
    :func:`~latentforce.inference.pgas_defaults.default_residual_steps`) move the ``residual_modes`` slowest
    modes of the mechanical within-step noise, the force following so that
    the acceleration predictions are kept; where the system has internal
    (hysteretic) states, the initial prior leaves them free of the displacements
    and velocities (:func:`~latentforce.inference.internal_move.free`) and no
    system parameter is sampled, ``internal_steps`` steps of their start-up move
    follow (:mod:`latentforce.inference.internal_move`; 0 disables: their
    initial values stepped with the displacements, velocities and
    accelerometer residuals held), then ``profile_steps`` steps of the profile
    move (:mod:`latentforce.inference.profile_move`; 0 disables; None: its
    default); where system parameters are sampled, the
    system move's walk carries those initial values instead (0 disables that
    too: :func:`~latentforce.inference.pgas_block.system_internal`), and each
    chain starts from a path of its own model (Gauss-Newton at its dispersed
    system parameters). Before those, right after the
    sweep, ``smoother_steps`` Metropolis-Hastings steps
    (:mod:`latentforce.inference.smoother_move`; 0 disables; None:
    :func:`~latentforce.inference.pgas_defaults.default_smoother_steps`; an independence
    step, then Crank-Nicolson steps, :data:`~latentforce.inference.smoother_move.CN_BETAS`)
    propose whole paths from the linearised model's smoother about each chain's centre
    (Gauss-Newton from the extended Kalman smoother, for nonlinear systems
    re-set from the chain's path where the path moves are re-shaped in the
    burn-in): exact draws for a linear system, and most proposals accepted
    where the posterior is close to Gaussian (a displacement channel), which
    the sweep of a smooth force no longer renews. On a long record the smoother move's whole-path
    proposals accept less (their weight's variance grows with T); ``window`` (a width in samples) then
    adds one pass of the window move after it (:mod:`latentforce.inference.window_move`: a bridge
    through one window at a time, the path on both sides held; 0 disables; None:
    :func:`~latentforce.inference.pgas_defaults.default_window`), and the sweep then runs with fewer
    ``particles`` (None: :func:`~latentforce.inference.pgas_defaults.default_particles`, 50 and 16 with
    the window move; the count used is ``diagnostics["particles"]``). With free hyperparameters or system
    parameters each block starts with ``joint_steps`` joint Metropolis-Hastings steps on :math:`(\theta, \text{path})`
    (0 disables; three, not one: on a Duffing record with c, k3, both hyperparameters free and a
    displacement channel, three steps gave three times the parameters' ESS for 7 % more time;
    the system parameters move only here): a random walk on :math:`\theta` whose path is drawn from the same
    smoother at the proposed :math:`\theta`, accepted on the linearised marginal likelihood
    corrected by the smoother move's weights (:mod:`latentforce.inference.smoother_move`,
    "The joint move"); given a path the hyperparameters are pinned (a smooth force's path
    fixes :math:`\sigma_f^2/\ell^{2\nu}`), and this move is what lets them mix.
    ``initial = (mean, sd)`` or ``(mean, cov)`` of the initial mechanical state, else the
    default of :class:`particle_model.ParticleModel` (linear systems: the joint stationary
    start at the current hyperparameters). ``progress(done, total, accept_rate)`` is called
    between scan chunks.

    ``iterations=None`` ("auto"): after the burn-in, run in chunks of
    ``chunk_blocks`` blocks (at most ``max_iterations`` iterations) and stop
    once the convergence verdict of
    :func:`latentforce.inference.convergence.diagnose` holds (worst R-hat <=
    1.01, bulk ESS >= ``target_ess``) over the hyperparameters (noise levels included) and the
    displacement, velocity and force at 24 monitored times (recorded at every
    sweep, not thinned), or once ``max_time`` seconds have passed since the
    start. The verdict (of any run, "auto" or not) is in
    ``diagnostics["convergence"]``, its states labelled by time index. At most
    ``thin_draws`` paths per chain are stored: when they would overflow, every
    other one is dropped and the stride doubles.

    ``channels``: ``(quantity, dof)`` pairs through which the compiled programs
    observe the system (default: the sensors'; :func:`observe_through`).
    Channels no sensor reads are never observed, so the posterior is the same
    (the draws too, unless an unobserved channel is the one that lets the
    residual-preserving move apply, or an unobserved displacement or strain channel
    sets the path moves' default step counts,
    :func:`~latentforce.inference.pgas_defaults.default_smoother_steps`,
    :func:`~latentforce.inference.pgas_defaults.default_window` and
    :func:`~latentforce.inference.pgas_defaults.default_residual_steps`: exact moves either way, so still the same
    posterior); two runs whose models differ only in their sensors' names and
    noise then have one structure and share every compiled program.

    **Compiled once per structure.** The programs are module-level ``jit``
    functions (:func:`_run_chunk`, :func:`_shapes` ...) that take every number
    as an argument (the record, the noise covariance, and the model's numbers
    in :class:`~particle_model.ParticleModel`, :class:`Hyper`,
    :class:`ResidualMove` and :class:`~noise_gibbs.NoiseLevels`, pytrees whose
    leaves are numbers) and the structure and settings as static arguments, so
    a second run of one structure and shape compiles nothing, whatever its
    numbers (``tests/test_pgas_compile_once.py``).

    ``checkpoint`` (:class:`latentforce.checkpoint.Checkpoint`, or None) is
    offered the loop state after every segment of blocks (the segments are
    fixed by the settings; each chain carries its own key), and a run
    restored from it continues exactly as the uninterrupted one
    (:mod:`latentforce.inference.resume`).
    """
    if channels is not None:
        model, y, mask = observe_through(model, channels, y, mask)
    y = jnp.asarray(y, dtype=float)
    mask = jnp.asarray(mask, dtype=bool) & jnp.isfinite(y)
    noise = noise_gibbs.noise_levels(model, free, mask)
    hyper = Hyper(
        params,
        {n: v for n, v in free.items() if n not in noise.names},
        model.system.param_names,
        hyper_names(model.kernel, split=True),
    )
    params = {**params, **dict(zip(hyper.sys_names, hyper.sys_init))}
    d = len(hyper.joint_names)
    start_record, spread, joint_chol = None, pgas_mode.START_SPREAD * np.eye(d), pgas_mode.WALK_SD * np.eye(d)
    x0 = hyper.joint_coordinates(np.concatenate([hyper.init, hyper.sys_init])) if d else jnp.zeros(0)
    # the model at the system parameters' initial values: its initial-state prior (a nonlinear
    # system's default depends on c and k) is kept while they are sampled (ParticleModel.with_params)
    pm = particle_model.ParticleModel(
        _unnamed(model), params, dt, discretisation, initial, R=model.noise_covariance(params)
    )
    if hyper.sys_names:  # start at the filter's posterior mode (pgas_mode), with the same prior
        R0 = jnp.diag(noise_gibbs.initial_variances(noise, pm.R)) if noise.channels else pm.R
        kept = None if pm.stationary_start else (pm.mech0_mean, pm.mech0_cov)
        x0, cov, start_record = pgas_mode.mode_start(
            _unnamed(model), hyper, params, y, mask, R0, dt, discretisation, kept
        )
        spread, joint_chol = 2.0 * np.linalg.cholesky(cov), 2.38 / np.sqrt(d) * np.linalg.cholesky(cov)
        # the smoother's start and the shapes at the mode; each chain then carries its own (Hyper.model_at)
        pm = pm.with_params({n: float(v) for n, v in hyper.system_values(jnp.asarray(x0[len(hyper.names) :])).items()})
    T = y.shape[0]
    t_start = time.perf_counter()
    auto = iterations is None
    if auto:
        # the blocks are laid out for the cap; the stride of the stored paths starts at one
        sched = schedule(burn_in, max_iterations, state_every, mh_steps, thin_draws)
        sched = sched._replace(thin=1, n_draws=max(2, int(thin_draws)))
        chunk_blocks = min(int(chunk_blocks), max(50, sched.burn_blocks // 2))
    else:
        sched = schedule(burn_in, iterations, state_every, mh_steps, thin_draws)
    tpoints = np.unique(np.linspace(0, T - 1, time_points).round().astype(int))
    mpoints = convergence.monitored_times(T)
    basis = lowfreq_basis(T, lowfreq_modes)

    # ---- initialisation (outside the loop; never from the truth), in compiled programs:
    # run op by op it compiled some hundred tiny programs, most of a quick run's start-up
    R = pm.R if not noise.channels else jnp.diag(noise_gibbs.initial_variances(noise, pm.R))
    od = _observation_density(pm, y, mask, R)
    k_theta, k_chains = jax.random.split(key)
    xs0, tr0, trs0 = _start_transitions(k_theta, jnp.asarray(x0), jnp.asarray(spread), pm, hyper, chains=int(chains))
    rm = ResidualMove(pm, T, residual_modes, np.sqrt(np.diagonal(np.asarray(tr0.Q))[pm.latent_layout.noise]))
    if smoother_steps is None:
        smoother_steps = default_smoother_steps(pm)
    if profile_steps is None:
        profile_steps = profile_move.PROFILE_STEPS
    if residual_steps is None:
        residual_steps = default_residual_steps(pm, smoother_steps)
    if window is None:
        window = default_window(pm, T, smoother_steps)
    if particles is None:
        particles = default_particles(window)
    with_rp = rm.applies and int(residual_steps) > 0
    # the block's settings (static): make_block checks the step counts, here before any compile
    block_settings = dict(
        particles=int(particles),
        proposal=proposal,
        resampling=resampling,
        ancestor_sampling=bool(ancestor_sampling),
        unroll=int(unroll),
        interweave=bool(interweave),
        lowfreq_steps=int(lowfreq_steps),
        residual_steps=int(residual_steps),
        smoother_steps=int(smoother_steps),
        window=int(window),
        joint_steps=int(joint_steps),
        system_steps=int(system_steps),
        # the start-up move where the initial prior leaves the internal states free (internal_move.free;
        # a negative count is make_block's error)
        internal_steps=int(internal_steps) if int(internal_steps) < 0 or internal_move.free(pm) else 0,
        # the profile move likewise (profile_move; a negative count is make_block's error)
        profile_steps=int(profile_steps) if int(profile_steps) < 0 or internal_move.free(pm) else 0,
        recentre=int(joint_recentre),
    )
    make_block(pm, hyper, sched, rm, basis, tpoints, mpoints, noise=noise, **block_settings)
    block_static = dict(
        sched=sched,
        tpoints=tuple(int(t) for t in tpoints),
        mpoints=tuple(int(t) for t in mpoints),
        settings=tuple(sorted(block_settings.items())),
    )
    eks, ref_q = _smooth(pm, y, mask, R, tr0)
    # The chains' start and the moves' first shapes: for a nonlinear system the extended smoother's
    # mean is no path of the model (its mechanical innovations, whitened, reached 3e4 sds on the
    # frame: a log prior 4e9 below the mode's), and chains started from it relaxed in whatever
    # direction their first moves took, two of four on the frame far off into a region they never
    # left. Gauss-Newton from it (the smoother move's centre, a path of the model with the same fit)
    # is where they start; for a linear system the two coincide (no iterations).
    one = jax.tree_util.tree_map(lambda a: a[None], (tr0, eks))
    start = _centres(pm, od, *one, hyper, np.zeros((1, 0)), iterations=_centre_iterations(pm))[0]

    def per_chain(a):
        return np.broadcast_to(np.asarray(a), (chains,) + np.shape(a))

    if hyper.sys_names and not pm.is_linear:
        # Each chain starts from a path of its own model: its system parameters are dispersed about
        # the mode, and the start path is the mode's. A nonlinear system's path depends on them (a
        # Bouc-Wen r on gamma): on the gamma record of tests/test_signed_priors.py one chain, 50
        # iterations after a start on the mode's path, still had its hysteretic state's within-step
        # noise 26 times its typical sum of squares (a log target 4 500 below the other chains'),
        # and with r0 moved it stayed near there for the test's 1 000 iterations (docs/nonlinear.md).
        # Gauss-Newton from the mode's path on each chain's model (the smoother move's centre
        # between burn-in chunks) is its start, its shapes and centre.
        xs_sys0 = np.asarray(xs0)[:, len(hyper.names) :]
        starts = _centres(pm, od, trs0, per_chain(start), hyper, xs_sys0, iterations=_centre_iterations(pm))
        lfs, rps = _shapes(pm, rm, basis, od, trs0, starts, hyper, xs_sys0, with_rp=with_rp)
    else:
        starts = per_chain(start)
        none = np.zeros((chains, 0))  # the shapes and centre at the starting model
        lfs, rps = _shapes(
            pm, rm, basis, od, jax.tree_util.tree_map(per_chain, tr0), starts, hyper, none, with_rp=with_rp
        )
    with_sm = int(smoother_steps) > 0
    centres = starts if with_sm else None
    # the system move's walk on the internal states' initial offsets too (system_moves): its first
    # guess of their variance, the share of the initial prior's that the motion leaves free
    n_sys_int = system_internal(pm, rm, len(hyper.sys_names), system_steps, block_settings["internal_steps"])
    int_var = jnp.asarray(internal_move.free_share(pm)[:n_sys_int])
    states = init_chains(
        pm,
        hyper,
        noise,
        basis,
        k_chains,
        tr0,
        jnp.asarray(starts),
        xs0,
        trs0,
        lfs,
        rps,
        R,
        od,
        centres,
        jnp.asarray(joint_chol),
        int_var,
        chains=int(chains),
        sched=sched,
    )

    n_blocks = sched.n_blocks
    scan_len, segments, reshape_at = reshape_chunks(n_blocks, sched.burn_blocks, chunk_blocks, not pm.is_linear)

    # the data are arguments, not constants of the program: a compiled program (and
    # JAX's persistent cache entry) then serves every record of the same shape
    data = BlockData(y, mask, od, ref_q)

    infos = []
    verdict, done, finished, stopped, cut = None, 0, False, None, None
    saved = checkpoint.restore("pgas") if checkpoint is not None else None
    if saved is not None:
        states, infos, ref_q, done, finished, stopped, cut = pgas_restore(saved, states, BlockInfo)
        data = data._replace(ref_q=ref_q)
        t_start = time.perf_counter() - saved.elapsed_s
    # "auto": a warm-up still running at half of max_time stops at that segment's end (cut_warm_up), once
    # it has run its floor
    warm_up_cap = convergence.WARM_UP_SHARE * max_time if auto else float("inf")
    for start, end in segments:
        off = 0 if cut is None else sched.burn_blocks - cut  # the blocks' numbers in the compiled schedule
        if finished or start + off >= n_blocks:
            break
        end = min(end, n_blocks - off)
        if end <= done:  # run before the checkpoint this run was restored from
            continue
        if start in reshape_at and cut is None:  # new shapes, the adapted scales kept, at each chain's own model
            x_sys = _chain_system(states, hyper)
            lfs, rps = _shapes(pm, rm, basis, od, states.tr, states.reference, hyper, x_sys, with_rp=with_rp)
            states = states._replace(
                rwm_lf=_with_scale_of(lfs, states.rwm_lf), rwm_rp=_with_scale_of(rps, states.rwm_rp)
            )
            if with_sm:  # the smoother move's centre: Gauss-Newton from each chain's own path
                states = states._replace(
                    centre=_centres(
                        pm, od, states.tr, states.reference, hyper, x_sys, iterations=_centre_iterations(pm)
                    )
                )
        if auto:
            states = fit_draws(states, end + off - sched.burn_blocks, sched.n_draws)
        states, info = _run_chunk(
            states,
            np.arange(start + off, start + off + scan_len, dtype=np.int32),
            np.int32(end + off),
            data,
            pm,
            hyper,
            rm,
            basis,
            noise,
            **block_static,
        )
        infos.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[:, : end - start], info))
        done = end
        if progress is not None:
            acc = float(np.mean(infos[-1].accept))
            progress(end * sched.state_every, (n_blocks - off) * sched.state_every, acc)
        finished = end + off >= n_blocks
        floor = convergence.WARM_UP_FLOOR * sched.burn_blocks
        if floor <= end + off < sched.burn_blocks and time.perf_counter() - t_start >= warm_up_cap:
            cut = end
        if auto and end + off >= first_check(sched, cut):
            verdict = _verdict(pm, hyper, infos, cut_warm_up(sched, cut), mpoints, target_ess, noise.names)
            if verdict["converged"] or time.perf_counter() - t_start > max_time:
                stopped = "converged" if verdict["converged"] else "max_time"
                finished = True
        if checkpoint is not None:
            checkpoint.save(
                "pgas",
                lambda: pgas_loop_state(
                    states, infos, ref_q, done, finished, stopped, time.perf_counter() - t_start, cut
                ),
            )
    info = jax.tree_util.tree_map(lambda *a: np.concatenate(a, axis=1), *infos)  # the segments tile the blocks
    run = cut_warm_up(sched, cut)  # the schedule as run: its warm-up cut short where max_time did
    total = min(run.total, done * sched.state_every)
    post_sweeps = max(0, done - run.burn_blocks)
    thin = int(np.asarray(states.thin).reshape(-1)[0])
    n_draws = min(sched.n_draws, -(-post_sweeps // thin))
    out = _assemble(pm, hyper, states, info, ref_q, run.burn_in, total, run.burn_blocks, n_draws, tpoints, noise.names)
    out.diagnostics["thin"] = thin
    out.diagnostics["particles"] = int(particles)
    if start_record is not None:
        out.diagnostics["start"] = start_record
    out.diagnostics["iterations_run"] = max(0, total - run.burn_in)
    out.diagnostics["burn_in_run"] = run.burn_in
    if verdict is None:
        verdict = _verdict(pm, hyper, infos, run, mpoints, target_ess, noise.names)
    out.diagnostics["convergence"] = verdict
    if auto:
        out.diagnostics["stopped"] = stopped or (
            "converged"
            if verdict["converged"]
            else "max_time"
            if time.perf_counter() - t_start > max_time
            else "max_iterations"
        )
    return out


# ---------------------------------------------------------------------------
# The compiled programs: module-level, the model's numbers (pm, hyper, rm, noise: pytrees whose
# leaves are numbers) and the record as arguments, the structure and the settings static. JAX's
# own cache then serves every run of one structure and shape: a campaign's second record
# compiles nothing (tests/test_pgas_compile_once.py, benchmarks/compile_counts.py).
# ---------------------------------------------------------------------------
@jit
def _observation_density(pm, y, mask, R):
    return observation_density(pm, y, mask, R)


@jit
def _smooth(pm, y, mask, R, tr0):
    """The extended Kalman smoother's path at theta_0, and its summary quantities (``ref_q``:
    the centring of the running sums, for numerical stability)."""
    eks = extended_kalman_smoother(pm, tr0, y, mask, R)
    return eks, _summary_quantities(pm, eks)


def _chain_system(states: ChainState, hyper: Hyper):
    """Each chain's sampled system parameters (log space; ``(chains, 0)`` when none is sampled)."""
    chains = states.key.shape[0]
    if not hyper.sys_names:
        return np.zeros((chains, 0))
    return states.rwm_joint.x[:, len(hyper.names) :]


def _at(pm, hyper, x_sys):
    """``pm`` at the system parameters ``x_sys`` (``pm`` itself for an empty ``x_sys``)."""
    return hyper.model_at(pm, x_sys) if x_sys.shape[-1] else pm


@functools.partial(jit, static_argnames=("with_rp",))
def _shapes(pm, rm, basis, od, trs, paths, hyper, x_sys, *, with_rp):
    """The path moves' shapes at each chain's path and model (``x_sys``: its system parameters).
    One program (Gauss-Newton, a Jacobian through the path rebuild: a large program) for the
    smoother's path and, for nonlinear models, each chain's path between burn-in chunks; inside
    the block it compiled again."""

    def one(tr_, x_, xs):
        pm_c = _at(pm, hyper, xs)
        return path_move_shapes(pm_c, rm.at(pm_c) if xs.shape[-1] else rm, basis, od, tr_, x_, with_rp)

    return jax.vmap(one)(trs, paths, x_sys)


def _centre_iterations(pm) -> int:
    """Gauss-Newton iterations for the smoother move's centre: none for a linear system (its
    expansion is exact about any path), else :data:`smoother_move.CENTRE_ITERATIONS`."""
    return 0 if pm.is_linear else smoother_move.CENTRE_ITERATIONS


@functools.partial(jit, static_argnames=("iterations",))
def _centres(pm, od, trs, paths, hyper, x_sys, *, iterations):
    """The smoother move's centres (:func:`smoother_move.iterated_centre`) from ``paths``, one per
    transition in ``trs`` and system parameters in ``x_sys`` (leading axis): Gauss-Newton on each
    chain's own model, so that a chain whose stiffness is far from the start's gets proposals that
    fit it."""
    return jax.vmap(lambda tr, x, xs: smoother_move.iterated_centre(_at(pm, hyper, xs), tr, od, x, iterations))(
        trs, paths, x_sys
    )


@functools.partial(jit, static_argnames=("sched", "tpoints", "mpoints", "settings"))
def _run_chunk(states, blocks, end, data, pm, hyper, rm, basis, noise, *, sched, tpoints, mpoints, settings):
    """The Gibbs blocks ``blocks`` of every chain (vmapped), those at or past ``end`` skipped
    (:func:`reshape_chunks`); the block is built here, from the traced model, by :func:`make_block`."""
    block = make_block(
        pm,
        hyper,
        sched,
        rm,
        basis,
        np.asarray(tpoints, dtype=int),
        np.asarray(mpoints, dtype=int),
        noise=noise,
        **dict(settings),
    )
    # traced once: for the shapes of the output (the skipped blocks') and in the scan
    vblock = jax.jit(jax.vmap(block, (0, None, None)))
    info_shapes = jax.eval_shape(vblock, states, jax.ShapeDtypeStruct((), jnp.int32), data)[1]

    def skip(s):
        return s, jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), info_shapes)

    def body(s, b):
        return jax.lax.cond(b < end, lambda s_: vblock(s_, b, data), skip, s)

    states, info = jax.lax.scan(body, states, blocks)
    return states, jax.tree_util.tree_map(lambda a: jnp.swapaxes(a, 0, 1), info)  # chains first


def fit_draws(states: ChainState, post_sweeps: int, n_slots: int) -> ChainState:
    """Make room for ``post_sweeps`` post-burn-in sweeps in ``n_slots`` stored paths: while they
    would not fit, keep every other stored path and double the stride (slot ``j`` then holds
    sweep ``j * thin`` as before)."""
    thin = int(np.asarray(states.thin).reshape(-1)[0])
    draws = states.draws
    while -(-post_sweeps // thin) > n_slots:
        kept = draws[:, 0:n_slots:2]
        draws = jnp.zeros_like(draws).at[:, : kept.shape[1]].set(kept)
        thin *= 2
    return states._replace(draws=draws, thin=jnp.full_like(states.thin, thin))
