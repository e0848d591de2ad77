r"""Blocked particle Gibbs for joint input-state-hyperparameter estimation (Algorithm 5, Vibration 2020).

Each Gibbs block is one PGAS sweep (:mod:`latentforce.inference.smc`) for the
trajectory :math:`x_{1:T}` given :math:`\theta`, then ``state_every``
iterations of Metropolis-within-Gibbs for the GP hyperparameters
:math:`\theta \subseteq \{\sigma_f^2, \ell\}` given the trajectory
(Eq. 23-25), each of ``mh_steps`` random-walk steps. Because the mechanical
map :math:`\Phi` does not depend on :math:`\theta`, the observation terms of
Eq. (25) cancel and the MH target is the density of the latent path
:math:`g = (x_f, w)` (force states and within-step mechanical noise,
:mod:`smc`) times the prior.

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
``colour`` and :meth:`~smc.ParticleModel.path`; the proposal's shape is a
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

**Priors.** Along that ridge the path density tends to a constant once
:math:`\ell` exceeds the record length (a long-lengthscale Matérn-1/2 path
is Brownian motion over the record), so the ridge's tail is held only by
the prior: a flat prior on :math:`\sigma_f^2` contributes a factor
:math:`\sigma_f^2 \propto \ell` in log space and puts the posterior at
lengthscales far beyond the record (Duffing case, 0.5 s record: posterior
median :math:`\ell` of several seconds). Use a proper prior on
:math:`\sigma_f^2` or :math:`\ell` when the record spans few lengthscales.

One Gibbs block of one chain is :func:`make_block` (a pure function of the chain
state, the block index and the data); :func:`run_pgas` initialises the chains,
``jax.vmap``-s the block over them and runs the blocks in a ``lax.scan``; Python only
chunks the scan for progress reports. Initialisation never uses the truth:
an extended Kalman smoother at the initial :math:`\theta` gives a path that
fits the data; each chain starts from it moved by twice its Gauss-Newton
posterior sd in the low-frequency coordinates (:func:`dispersed_start`,
different per chain), and from :math:`\theta_0 \exp(0.5\,\varepsilon)` per
parameter.

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

import math
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.compile import shared_jit
from latentforce.inference import convergence, mcmc, smc
from latentforce.inference.hyper_moves import (
    _RESHAPE_AT,
    Hyper,
    adaptation_schedule,
    init_proposal,
    mh_step,
    noncentred_log_target,
    proposal_covariance,
)
from latentforce.inference.latent import (
    ObservationDensity,
    observation_density,
    observation_log_likelihood,
    whiten,
)
from latentforce.inference.path_moves import (
    LowFrequencyFrame,
    ResidualMove,
    lowfreq_basis,
    lowfreq_init,
    lowfreq_move,
    residual_init,
    residual_move,
)
from latentforce.inference.pgas_start import dispersed_start, extended_kalman_smoother
from latentforce.inference.resume import pgas_loop_state, pgas_restore

# ---------------------------------------------------------------------------
# Hyperparameter step (Eq. 23-25)
# ---------------------------------------------------------------------------


# ---------------------------------------------------------------------------
# Non-centred (interweaving) step: Yu & Meng (2011), ASIS
# ---------------------------------------------------------------------------


# ---------------------------------------------------------------------------
# Low-frequency trajectory move in the non-centred coordinates
# ---------------------------------------------------------------------------


# ---------------------------------------------------------------------------
# Residual-preserving trajectory move
# ---------------------------------------------------------------------------


# ---------------------------------------------------------------------------
# Initialisation: extended Kalman smoother
# ---------------------------------------------------------------------------


# ---------------------------------------------------------------------------
# The blocked Gibbs sampler
# ---------------------------------------------------------------------------
class ChainState(NamedTuple):
    """State of one chain between Gibbs blocks (a pytree; vmapped over chains)."""

    key: Array
    reference: Float[Array, "T n"]
    rwm: mcmc.RWMState  # hyperparameters x = log(theta) and their centred random walk's adaptation
    rwm_nc: mcmc.RWMState  # the non-centred (interweaving) random walk's adaptation; its x mirrors rwm.x
    rwm_lf: mcmc.RWMState  # the low-frequency trajectory move's adaptation (x: its last coordinates)
    rwm_rp: mcmc.RWMState  # the residual-preserving move's adaptation
    # the latent's transition at rwm.x, carried so that a compiled block evaluates the
    # transition at only two places (its matrix exponentials were 40 % of the program)
    tr: smc.Transition
    block: Array  # Gibbs block counter
    # running sums over post-burn-in state samples: (z, v, u) per time
    sum1: Float[Array, "T q"]
    sum2: Float[Array, "T q"]
    count: Float[Array, ""]
    draws: Float[Array, "S T n"]  # thinned trajectories (last slot is a discard slot)
    thin: Array  # every thin-th post-burn-in sweep is stored (doubled by run_pgas as "auto" runs on)


class BlockInfo(NamedTuple):
    theta: Float[Array, "k p"]
    accept: Float[Array, " k"]
    accept_noncentred: Float[Array, " k"]
    accept_lowfreq: Float[Array, ""]
    accept_residual: Float[Array, ""]
    log_likelihood: Float[Array, ""]
    switch_rate: Float[Array, ""]
    ess: Float[Array, ""]
    force_points: Float[Array, "P nforce"]
    monitored: Float[Array, "M q"]  # displacement, velocity, force at the monitored times


class BlockData(NamedTuple):
    """The record and what is precomputed from it (arguments of the compiled programs)."""

    y: Float[Array, "T d"]
    mask: Array
    R: Float[Array, "d d"]  # the channels' noise covariance
    od: ObservationDensity
    ref_q: Float[Array, "T q"]  # centring of the running sums (the smoother's summary quantities)


class PGASOutput(NamedTuple):
    """What :func:`run_pgas` returns (NumPy arrays; ``chains`` leading)."""

    names: tuple  # free hyperparameter names
    theta: dict  # name -> (chains, iterations), post burn-in
    theta_burn: dict  # name -> (chains, burn_in)
    trajectories: np.ndarray  # (chains, draws, T, n_state), thinned, post burn-in
    state_mean: dict  # "displacement" | "velocity" | "force" -> (T, ndof|nforce), all post-burn-in sweeps
    state_sd: dict
    acceptance: np.ndarray  # (chains,), post burn-in MH acceptance rate
    switch_rate: np.ndarray  # (chains, sweeps) post burn-in AS switch fraction per sweep
    ess: np.ndarray  # (chains, sweeps) mean ESS/N of the filter per sweep
    log_likelihood: np.ndarray  # (chains, sweeps) PF estimate log p(y | theta) per sweep
    force_points: np.ndarray  # (chains, sweeps, P, nforce) force at `time_points`
    time_points: np.ndarray
    diagnostics: dict
    mh_scale: np.ndarray  # (chains, p) frozen random-walk proposal sd per parameter (log space)


def _summary_quantities(pm: smc.ParticleModel, path: Float[Array, "T n"]):
    nd = pm.ndof
    force_idx = pm.nm + pm.kdim * np.arange(pm.nforce)
    return jnp.concatenate([path[:, :2 * nd], path[:, force_idx]], axis=1)


class Schedule(NamedTuple):
    """Iteration bookkeeping of a Gibbs run (static integers; :func:`schedule`)."""

    state_every: int
    mh_steps: int
    burn_in: int  # iterations
    total: int  # iterations, burn-in included
    n_blocks: int  # Gibbs blocks, one sweep each
    burn_blocks: int  # blocks whose sweep is at an iteration < burn_in (they adapt)
    thin: int  # every thin-th post-burn-in path is stored
    n_draws: int  # stored paths


def schedule(burn_in: int, iterations: int, state_every: int = 1, mh_steps: int = 1,
             thin_draws: int = 200) -> Schedule:
    """The blocks of a run of ``burn_in + iterations`` iterations, a sweep on every ``state_every``-th."""
    k_every, n_mh = int(state_every), int(mh_steps)
    if n_mh < 1:
        raise ValueError(f"mh_steps must be at least 1, got {mh_steps}")
    if k_every < 1:
        raise ValueError(f"state_every must be at least 1, got {state_every}")
    total = int(burn_in) + int(iterations)
    n_blocks = -(-total // k_every)
    burn_blocks = -(-int(burn_in) // k_every)
    post_sweeps = n_blocks - burn_blocks
    thin = max(1, -(-post_sweeps // max(1, int(thin_draws))))
    n_draws = -(-post_sweeps // thin) if post_sweeps > 0 else 0
    return Schedule(k_every, n_mh, int(burn_in), total, n_blocks, burn_blocks, thin, n_draws)


def path_move_shapes(pm: smc.ParticleModel, rm: ResidualMove, basis, od: ObservationDensity,
                     tr: smc.Transition, path: Float[Array, "T n"], with_residual: bool
                     ) -> tuple[mcmc.RWMState, mcmc.RWMState]:
    """Fresh low-frequency and residual-preserving walks shaped at ``path`` (:func:`lowfreq_init`,
    :func:`residual_init`); without the residual move its walk is a copy of the other."""
    lf = lowfreq_init(pm, od, LowFrequencyFrame(tr, basis), path)
    return lf, (residual_init(rm, pm, od, tr, path) if with_residual else lf)


def reshape_chunks(n_blocks: int, burn_blocks: int, chunk_blocks: int, nonlinear: bool
                   ) -> tuple[int, list[tuple[int, int]], tuple[int, ...]]:
    """``(scan_len, segments, reshape_at)``: how :func:`run_pgas` runs its blocks.

    ``segments``: the ``(start, end)`` runs of blocks, each one call of one
    compiled program that scans ``scan_len >= end - start`` blocks and skips
    those at or past ``end``. ``reshape_at``: the blocks before which the path
    moves are re-shaped at each chain's path. For a linear model the
    Gauss-Newton shapes from the smoother are exact and nothing is re-shaped.
    For a nonlinear one the chain's path moves away from the smoother's, so the
    shapes are re-computed at fractions ``_RESHAPE_AT`` of the burn-in, by a
    program of their own shared with the start: inside the block (under a
    conditional) they added a quarter to its compile time. A scan of fixed
    length with skipped iterations, not one program per segment length: XLA
    unrolls short scans, and the block compiled twice as long at length 2.
    """
    chunk_blocks = max(1, int(chunk_blocks))
    scan_len = -(-n_blocks // max(1, -(-n_blocks // chunk_blocks)))
    at = () if not nonlinear else tuple(sorted(
        {int(math.ceil(f * burn_blocks)) - 1 for f in _RESHAPE_AT if 1 <= math.ceil(f * burn_blocks) - 1}))
    bounds = sorted(set(range(0, n_blocks, scan_len)) | {b for b in at if b < n_blocks} | {n_blocks})
    return scan_len, list(zip(bounds[:-1], bounds[1:])), at


def _with_scale_of(fresh: mcmc.RWMState, adapted: mcmc.RWMState) -> mcmc.RWMState:
    """``fresh``'s shape with ``adapted``'s scale and adaptation count (the re-shaping keeps the scale)."""
    return fresh._replace(log_scale=adapted.log_scale, count=adapted.count)


def make_block(pm: smc.ParticleModel, hyper: Hyper, sched: Schedule, rm: ResidualMove, basis, tpoints, mpoints, *,
               particles: int = 50, proposal: str = "optimal", resampling: str = "multinomial",
               ancestor_sampling: bool = True, unroll: int = 1, interweave: bool = True,
               lowfreq_steps: int = 5, residual_steps: int = 60) -> Callable:
    r"""``block(state, b, data) -> (state, BlockInfo)``: Gibbs block ``b`` of one chain (pure, jittable).

    A PGAS sweep at the carried transition; ``lowfreq_steps`` low-frequency
    moves (``basis``: :func:`lowfreq_basis`) and ``residual_steps``
    residual-preserving moves (``rm``; skipped where it does not apply); the
    post-burn-in running sums and thinned draws; then ``state_every``
    Metropolis-within-Gibbs iterations of ``mh_steps`` centred and (with
    ``interweave``) non-centred steps on :math:`\theta`. Blocks
    ``b < sched.burn_blocks`` adapt the proposals' scales; later blocks are a
    fixed kernel. The path moves' shapes are the caller's (for nonlinear
    systems :func:`run_pgas` re-computes them between burn-in blocks with
    :func:`path_move_shapes`). ``b`` must be shared by vmapped chains (it drives conditionals);
    ``data`` (:class:`BlockData`) may be shared or batched. ``tpoints``: the
    time indices whose force values are recorded.

    The caller's :class:`ChainState` must hold ``tr``, the transition at
    ``rwm.x``, and ``draws`` with ``sched.n_draws + 1`` slots (the last is a
    discard slot); ``data.ref_q`` centres the running sums (``(T, q)``, see
    :func:`run_pgas`). The walks' ``logdensity`` fields are refreshed before
    use. ``mpoints``: the time indices whose displacement, velocity and force are
    recorded every block (the convergence monitor). The stored-draw stride is the
    state's ``thin`` (``sched.thin`` at the start).
    """
    p = len(hyper.names)
    k_every, n_mh, burn_in = sched.state_every, sched.mh_steps, sched.burn_in
    n_blocks, burn_blocks, n_draws = sched.n_blocks, sched.burn_blocks, sched.n_draws
    sweep = smc.make_sweep(pm, particles, proposal=proposal, resampling=resampling, conditional=True,
                           ancestor_sampling=ancestor_sampling, unroll=unroll)
    target_acc = mcmc.target_acceptance(max(p, 1))
    reshape_steps = jnp.asarray(adaptation_schedule(burn_in * n_mh) or (-1,))
    n_lf, n_rp = int(lowfreq_steps), int(residual_steps)
    if n_lf < 0:
        raise ValueError(f"lowfreq_steps must be non-negative, got {lowfreq_steps}")
    if n_rp < 0:
        raise ValueError(f"residual_steps must be non-negative, got {residual_steps}")
    n_rp = n_rp if rm.applies else 0

    lf_reshape = jnp.asarray((-1,))
    interweave = bool(interweave) and p > 0

    def _block(state: ChainState, b, data: BlockData):
        """One Gibbs block of one chain (:func:`make_block`)."""
        key, k_sweep, k_mh, k_lf, k_rp = jax.random.split(state.key, 5)
        tr = state.tr
        sc = smc.sweep_constants(pm, tr, data.y, data.mask, proposal, data.R)
        out = sweep(k_sweep, sc, state.reference)
        path = out.trajectory
        rwm_lf, acc_lf = state.rwm_lf, jnp.zeros(())
        if n_lf:
            frame = LowFrequencyFrame(tr, basis)
            rwm_lf, path, accs_lf = lowfreq_move(k_lf, rwm_lf, pm, data.od, frame, path, n_lf, adapt=b < burn_blocks,
                                                 step0=b * n_lf, reshape_steps=lf_reshape)
            acc_lf = jnp.mean(accs_lf.astype(float))
        rwm_rp, acc_rp = state.rwm_rp, jnp.zeros(())
        if n_rp:
            rwm_rp, path, accs_rp = residual_move(k_rp, rwm_rp, rm, pm, data.od, tr, path, n_rp, adapt=b < burn_blocks)
            acc_rp = jnp.mean(accs_rp.astype(float))
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
                out_ = mh_step(kk, r_, target, adapt=j < burn_in,
                               reshape=jnp.any(j * n_mh + s_ == reshape_steps), target=target_acc, aux=a_)
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
                    return noncentred_log_target(hyper, pm, data.od, x, eps)

                # at the current point the rebuilt path is the current one (up to round-off);
                # the path is kept bit-for-bit when nothing moves (no round-off drift)
                rwm_nc = rwm_nc._replace(x=rwm.x, logdensity=hyper.log_prior(rwm.x)
                                         + observation_log_likelihood(pm, data.od, path_))
                rwm_nc, accs_nc, (g_, path_, tr_) = _steps(k_nc, rwm_nc, noncentred, j, aux=(g_, path_, tr_))
                rwm = rwm._replace(x=rwm_nc.x)
                acc_nc = jnp.mean(accs_nc.astype(float))
            return (rwm, rwm_nc, path_, g_, tr_), (rwm.x, jnp.mean(accs.astype(float)), acc_nc)

        js = b * k_every + jnp.arange(k_every)
        (rwm, rwm_nc, path_end, _, tr_end), (xs, accs, accs_nc) = jax.lax.scan(
            _mh_iter, (state.rwm, state.rwm_nc, path, pm.latent(path), tr), (jax.random.split(k_mh, k_every), js))
        theta = hyper.to_constrained(xs)
        fp = path[tpoints][:, pm.nm + pm.kdim * np.arange(pm.nforce)]
        new = ChainState(key, path_end, rwm, rwm_nc, rwm_lf, rwm_rp, tr_end, b + 1, sum1, sum2, state.count + wgt,
                         draws, state.thin)
        info = BlockInfo(theta, accs, accs_nc, acc_lf, acc_rp, out.info.log_likelihood, out.info.switched,
                         jnp.mean(out.info.ess), fp, _summary_quantities(pm, path)[mpoints])
        return new, info

    return _block


def observe_through(model, channels, y, mask):
    """``(model, y, mask)`` with the channels ``channels``, ``(quantity, dof)`` pairs, in that order.

    Each sensor moves to the channel of its quantity and DOF, with its noise;
    a channel no sensor reads gets a sensor of unit noise that is never
    observed (``y`` NaN, ``mask`` False there), which leaves the likelihood,
    hence the posterior, unchanged.
    """
    from latentforce.models import LatentForceModel, Sensor

    channels = [(str(q), int(d)) for q, d in channels]
    if len(set(channels)) != len(channels):
        raise ValueError(f"channels must be distinct, got {channels}")
    where = {c: i for i, c in enumerate(channels)}
    sensors = [Sensor(q, d, 1.0, f"unobserved {q} at DOF {d}") for q, d in channels]
    cols = []
    for s in model.sensors:
        i = where.get((s.quantity, s.dof))
        if i is None or i in cols:
            raise ValueError(f"channels {channels} have no channel of their own for the sensor {s}")
        cols.append(i)
        sensors[i] = s
    y, mask = np.asarray(y, dtype=float), np.asarray(mask, dtype=bool)
    if y.ndim != 2 or y.shape[1] != len(model.sensors) or mask.shape != y.shape:
        raise ValueError(f"y and mask must both be (T, {len(model.sensors)}), one column per sensor; "
                         f"got {y.shape} and {mask.shape}")
    y_all = np.full((y.shape[0], len(channels)), np.nan)
    mask_all = np.zeros(y_all.shape, dtype=bool)
    y_all[:, cols], mask_all[:, cols] = y, mask
    return LatentForceModel(model.system, model.kernel, sensors), y_all, mask_all


def run_pgas(key: Array, model, params: dict, free: dict, y, mask, dt: float, *,
             particles: int = 50, iterations: int | None = 1000, burn_in: int = 500, state_every: int = 1,
             chains: int = 4, mh_steps: int = 1, discretisation: str = "rk4", proposal: str = "optimal",
             resampling: str = "multinomial", thin_draws: int = 200, initial=None,
             progress: Callable | None = None, chunk_blocks: int = 1000, unroll: int = 1,
             time_points: int = 5, ancestor_sampling: bool = True, interweave: bool = True,
             lowfreq_modes: int = 16, lowfreq_steps: int = 5, residual_modes: int = 16,
             residual_steps: int = 60, channels=None, target_ess: float = 400.0, max_time: float = 600.0,
             max_iterations: int = 50_000, checkpoint=None) -> PGASOutput:
    r"""Blocked particle Gibbs (Algorithm 5, Vibration 2020) with the PGAS kernel of :mod:`smc`.

    ``params``: every model parameter (free hyperparameters too: their values
    are ignored except as fixed defaults). ``free``: ``name -> (prior, init)``
    for a subset of ``force_variance, force_lengthscale`` (may be empty: the
    trajectory is then sampled at fixed :math:`\theta`). ``y`` ``(T, d)`` may
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
    when no channel sees the force) move the ``residual_modes`` slowest
    modes of the mechanical within-step noise, the force following so that
    the acceleration predictions are kept. ``initial = (mean, sd)`` or ``(mean, cov)`` of
    the initial mechanical state, else the default of :class:`smc.ParticleModel`
    (linear systems: the joint stationary start at the current hyperparameters). ``progress(done,
    total, accept_rate)`` is called between scan chunks.

    ``iterations=None`` ("auto"): after the burn-in, run in chunks of
    ``chunk_blocks`` blocks (at most ``max_iterations`` iterations) and stop
    once the convergence verdict of
    :func:`latentforce.inference.convergence.diagnose` holds (worst R-hat <=
    1.01, bulk ESS >= ``target_ess``) over the hyperparameters and the
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
    residual-preserving move apply: an exact move either way, so still the same
    posterior); two runs whose models differ only in their sensors then compile the same
    programs, and run side by side in one process they compile them once
    (:func:`latentforce.compile.shared_jit`). The programs take the record and
    the noise covariance as arguments, never as constants.

    ``checkpoint`` (:class:`latentforce.checkpoint.Checkpoint`, or None) is
    offered the loop state after every segment of blocks (the segments are
    fixed by the settings; each chain carries its own key), and a run
    restored from it continues exactly as the uninterrupted one
    (:mod:`latentforce.inference.resume`).
    """
    if channels is not None:
        model, y, mask = observe_through(model, channels, y, mask)
    pm = smc.ParticleModel(model, params, dt, discretisation, initial)
    hyper = Hyper(params, free)
    y = jnp.asarray(y, dtype=float)
    mask = jnp.asarray(mask, dtype=bool) & jnp.isfinite(y)
    T = y.shape[0]
    p = len(hyper.names)
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
    nq = 2 * pm.ndof + pm.nforce
    basis = lowfreq_basis(T, lowfreq_modes)

    # ---- initialisation (outside the loop; never from the truth), in compiled programs:
    # run op by op it compiled some hundred tiny programs, most of a quick run's start-up
    x0 = hyper.to_unconstrained(hyper.init) if p else jnp.zeros(0)
    R = pm.R
    od = shared_jit(lambda y_, m_, R_: observation_density(pm, y_, m_, R_))(y, mask, R)
    k_theta, k_chains = jax.random.split(key)

    @shared_jit
    def _start_transitions(k):
        # the chains' dispersed starts theta_0 exp(0.5 eps), and the transitions at theta_0
        # and at those, from one place in the program (each place compiles its own matrix
        # exponentials: they dominated the compile time)
        xs = x0 + 0.5 * jax.random.normal(k, (chains, p))
        trs = jax.vmap(lambda x: pm.transition(*hyper.values(x)))(jnp.concatenate([x0[None], xs]))
        return xs, jax.tree_util.tree_map(lambda a: a[0], trs), jax.tree_util.tree_map(lambda a: a[1:], trs)

    xs0, tr0, trs0 = _start_transitions(k_theta)
    rm = ResidualMove(pm, T, residual_modes, np.sqrt(np.diagonal(np.asarray(tr0.Q))[pm.nfx:]))
    # (make_block checks the step counts)
    block = make_block(pm, hyper, sched, rm, basis, tpoints, mpoints, particles=particles, proposal=proposal,
                       resampling=resampling, ancestor_sampling=ancestor_sampling, unroll=unroll,
                       interweave=interweave, lowfreq_steps=lowfreq_steps, residual_steps=residual_steps)
    with_rp = rm.applies and int(residual_steps) > 0

    @shared_jit
    def _smooth(y, mask, R, tr0):
        eks = extended_kalman_smoother(pm, tr0, y, mask, R)
        # ref_q: centring of the running sums (numerical stability)
        return eks, _summary_quantities(pm, eks)

    # One program shapes the path moves (Gauss-Newton, a Jacobian through the path
    # rebuild: a large program) at the smoother's path and, for nonlinear models, at
    # each chain's path between burn-in chunks; inside the block it compiled again.
    @shared_jit
    def _shapes(od, trs, paths):
        return jax.vmap(lambda tr_, x_: path_move_shapes(pm, rm, basis, od, tr_, x_, with_rp))(trs, paths)

    @shared_jit
    def _init_chains(k_chains, tr0, eks, xs0, trs0, lfs, rps):
        frame0 = LowFrequencyFrame(tr0, basis)

        def _init_chain(ck, x, tr, lf, rp):
            k_path, k_run = jax.random.split(ck)
            ref = dispersed_start(k_path, pm, frame0, lf, eks)
            # the log density is set at the first block
            rwm = init_proposal(hyper, lambda x_: jnp.zeros(()), x)
            return ChainState(k_run, ref, rwm, rwm, lf, rp, tr, jnp.zeros((), jnp.int32),
                              jnp.zeros((T, nq)), jnp.zeros((T, nq)), jnp.zeros(()),
                              jnp.zeros((sched.n_draws + 1, T, pm.n_state)), jnp.asarray(sched.thin, jnp.int32))

        return jax.vmap(_init_chain)(jax.random.split(k_chains, chains), xs0, trs0, lfs, rps)

    eks, ref_q = _smooth(y, mask, R, tr0)

    def per_chain(a):
        return np.broadcast_to(np.asarray(a), (chains,) + np.shape(a))

    lfs, rps = _shapes(od, jax.tree_util.tree_map(per_chain, tr0), per_chain(eks))
    states = _init_chains(k_chains, tr0, eks, xs0, trs0, lfs, rps)

    n_blocks = sched.n_blocks
    scan_len, segments, reshape_at = reshape_chunks(n_blocks, sched.burn_blocks, chunk_blocks, not pm.is_linear)

    # the data are arguments, not constants of the program: a compiled program (and
    # JAX's persistent cache entry) then serves every record of the same shape
    data = BlockData(y, mask, R, od, ref_q)
    # traced once inside the chunk's trace: for the shapes of its output (the skipped
    # blocks') and in the scan
    vblock = jax.jit(jax.vmap(block, (0, None, None)))

    @shared_jit
    def _run_chunk(states, blocks, end, data):
        # here, not before: the whole trace then happens under the one lowering turn
        # (latentforce.compile.shared_jit)
        info_shapes = jax.eval_shape(vblock, states, jax.ShapeDtypeStruct((), jnp.int32), data)[1]

        def skip(s):
            return s, jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), info_shapes)

        def body(s, b):
            return jax.lax.cond(b < end, lambda s_: vblock(s_, b, data), skip, s)

        states, info = jax.lax.scan(body, states, blocks)
        return states, jax.tree_util.tree_map(lambda a: jnp.swapaxes(a, 0, 1), info)  # chains first

    infos = []
    verdict, done, finished, stopped = None, 0, False, None
    saved = checkpoint.restore("pgas") if checkpoint is not None else None
    if saved is not None:
        states, infos, ref_q, done, finished, stopped = pgas_restore(saved, states, BlockInfo)
        data = data._replace(ref_q=ref_q)
        t_start = time.perf_counter() - saved.elapsed_s
    # "auto": the verdict needs some draws; the first check after a tenth of the burn-in's sweeps
    first_check = sched.burn_blocks + max(20, sched.burn_blocks // 10)
    for start, end in segments:
        if finished:
            break
        if end <= done:  # run before the checkpoint this run was restored from
            continue
        if start in reshape_at:  # new shapes, the adapted scales kept
            lfs, rps = _shapes(od, states.tr, states.reference)
            states = states._replace(rwm_lf=_with_scale_of(lfs, states.rwm_lf),
                                     rwm_rp=_with_scale_of(rps, states.rwm_rp))
        if auto:
            states = fit_draws(states, end - sched.burn_blocks, sched.n_draws)
        states, info = _run_chunk(states, np.arange(start, start + scan_len, dtype=np.int32), np.int32(end), data)
        infos.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[:, :end - start], info))
        done = end
        if progress is not None:
            acc = float(np.mean(infos[-1].accept))
            progress(end * sched.state_every, n_blocks * sched.state_every, acc)
        finished = end >= n_blocks
        if auto and end >= first_check:
            verdict = _verdict(pm, hyper, infos, sched, mpoints, target_ess)
            if verdict["converged"] or time.perf_counter() - t_start > max_time:
                stopped = "converged" if verdict["converged"] else "max_time"
                finished = True
        if checkpoint is not None:
            checkpoint.save("pgas", lambda: pgas_loop_state(states, infos, ref_q, done, finished, stopped,
                                                            time.perf_counter() - t_start))
    info = jax.tree_util.tree_map(lambda *a: np.concatenate(a, axis=1), *infos)  # the segments tile the blocks
    total = min(sched.total, done * sched.state_every)
    post_sweeps = max(0, done - sched.burn_blocks)
    thin = int(np.asarray(states.thin).reshape(-1)[0])
    n_draws = min(sched.n_draws, -(-post_sweeps // thin))
    out = _assemble(pm, hyper, states, info, ref_q, sched.burn_in, total, sched.burn_blocks, n_draws, tpoints)
    out.diagnostics["thin"] = thin
    out.diagnostics["iterations_run"] = max(0, total - sched.burn_in)
    if verdict is None:
        verdict = _verdict(pm, hyper, infos, sched, mpoints, target_ess)
    out.diagnostics["convergence"] = verdict
    if auto:
        out.diagnostics["stopped"] = stopped or ("converged" if verdict["converged"] else "max_time"
                                                 if time.perf_counter() - t_start > max_time else "max_iterations")
    return out


def fit_draws(states: ChainState, post_sweeps: int, n_slots: int) -> ChainState:
    """Make room for ``post_sweeps`` post-burn-in sweeps in ``n_slots`` stored paths: while they
    would not fit, keep every other stored path and double the stride (slot ``j`` then holds
    sweep ``j * thin`` as before)."""
    thin = int(np.asarray(states.thin).reshape(-1)[0])
    draws = states.draws
    while -(-post_sweeps // thin) > n_slots:
        kept = draws[:, 0:n_slots:2]
        draws = jnp.zeros_like(draws).at[:, :kept.shape[1]].set(kept)
        thin *= 2
    return states._replace(draws=draws, thin=jnp.full_like(states.thin, thin))


def _verdict(pm: smc.ParticleModel, hyper: Hyper, infos: list, sched: Schedule, mpoints, target_ess: float) -> dict:
    """The convergence record over the post-burn-in draws so far (hyperparameters per
    iteration, the monitored displacement, velocity and force per sweep)."""
    info = jax.tree_util.tree_map(lambda *a: np.concatenate(a, axis=1), *infos)
    chains, blocks = info.accept.shape[:2]
    theta = np.reshape(info.theta, (chains, blocks * sched.state_every, -1))[:, sched.burn_in:sched.total]
    params = {n: theta[:, :, i] for i, n in enumerate(hyper.names)}
    mon = info.monitored[:, sched.burn_blocks:]  # (chains, sweeps, M, q)
    nd, nf = pm.ndof, pm.nforce
    columns = {"displacement": range(0, nd), "velocity": range(nd, 2 * nd), "force": range(2 * nd, 2 * nd + nf)}
    states = {}
    for name, cols in columns.items():
        for j, k in enumerate(cols):
            label = name if len(cols) == 1 else f"{name}_{j}"
            for i, t in enumerate(mpoints):
                states[f"{label}[t={int(t)}]"] = mon[:, :, i, k]
    return convergence.diagnose(params, states, target_ess=target_ess)


def _assemble(pm, hyper, states: ChainState, info: BlockInfo, ref_q, burn_in, total, burn_blocks,
              n_draws, tpoints) -> PGASOutput:
    chains = info.accept.shape[0]
    theta = np.reshape(info.theta, (chains, info.accept.shape[1] * info.accept.shape[2], len(hyper.names)))[:, :total]
    accept = np.reshape(info.accept, (chains, -1))[:, :total]
    th_post = {n: theta[:, burn_in:, i] for i, n in enumerate(hyper.names)}
    th_burn = {n: theta[:, :burn_in, i] for i, n in enumerate(hyper.names)}
    count = np.asarray(states.count)[:, None, None]
    s1 = np.asarray(states.sum1)
    s2 = np.asarray(states.sum2)
    # pool the chains: mean and sd over every post-burn-in state sample
    n_all = count.sum()
    mean_c = s1.sum(0) / n_all
    var = np.maximum(s2.sum(0) / n_all - mean_c**2, 0.0)
    mean = mean_c + np.asarray(ref_q)
    sd = np.sqrt(var)
    nd, nf = pm.ndof, pm.nforce
    sl = {"displacement": slice(0, nd), "velocity": slice(nd, 2 * nd), "force": slice(2 * nd, 2 * nd + nf)}
    state_mean = {k: mean[:, v] for k, v in sl.items()}
    state_sd = {k: sd[:, v] for k, v in sl.items()}
    cov = np.asarray(jax.vmap(proposal_covariance)(states.rwm))
    mh_sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    mh_corr = cov / np.maximum(mh_sd[:, :, None] * mh_sd[:, None, :], 1e-300)
    post = slice(burn_blocks, None)
    switch = info.switch_rate[:, post]
    ess = info.ess[:, post]
    fp = info.force_points[:, post]
    diag = {
        "acceptance": accept[:, burn_in:].mean(axis=1).tolist() if hyper.names else [],
        "switch_rate": switch.mean(axis=1).tolist(),
        "ess_per_particle": ess.mean(axis=1).tolist(),
        "nonfinite_log_likelihood": int(np.sum(~np.isfinite(info.log_likelihood))),
        "mh_proposal_sd": mh_sd.tolist(),
        "mh_proposal_corr": mh_corr.tolist(),
        "mh_sampling_space": "log",
        "acceptance_noncentred": np.reshape(info.accept_noncentred, (chains, -1))[:, burn_in:total].mean(axis=1).tolist()
        if hyper.names else [],
        "acceptance_lowfreq": info.accept_lowfreq[:, burn_blocks:].mean(axis=1).tolist(),
        "acceptance_residual": info.accept_residual[:, burn_blocks:].mean(axis=1).tolist(),
    }
    diag.update(convergence_diagnostics(th_post, fp, tpoints))
    return PGASOutput(hyper.names, th_post, th_burn, np.asarray(states.draws)[:, :n_draws], state_mean, state_sd,
                      accept[:, burn_in:].mean(axis=1) if hyper.names else np.zeros(chains), switch, ess,
                      info.log_likelihood[:, post], fp, tpoints, diag, mh_sd)


def convergence_diagnostics(theta: dict, force_points: np.ndarray, tpoints) -> dict:
    """R-hat and bulk ESS (arviz) of the hyperparameters and of the force at the recorded time points."""
    import warnings

    import arviz as az

    out = {"rhat": {}, "ess_bulk": {}}
    series = dict(theta)
    for j, t in enumerate(tpoints):
        for f in range(force_points.shape[-1]):
            series[f"force[{int(t)}]" + (f"[{f}]" if force_points.shape[-1] > 1 else "")] = force_points[:, :, j, f]
    for name, arr in series.items():
        if arr.shape[1] < 4:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out["rhat"][name] = float(az.rhat(np.asarray(arr)))
            out["ess_bulk"][name] = float(az.ess(np.asarray(arr)))
    return out


