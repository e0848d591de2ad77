r"""Exact inference for linear latent force models: ``kalman`` and ``kalman-mcmc``.

``kalman``: every parameter known; the Kalman filter and RTS smoother give
the exact posterior of the states and force, and the exact log-likelihood.

``kalman-mcmc`` (Algorithm 1, ISMA 2018): random-walk Metropolis over any
subset of the physical and GP parameters, in the softplus space of Eq. (27) (a signed
parameter: its standardised value, :mod:`latentforce.priors`),
with the Kalman filter's exact log-likelihood (the energy function, Eq.
24-26) plus the log prior and the log-Jacobian of the transform. Chains are
vmapped and the iterations scanned in chunks of one compiled program.

What makes it converge on long records (where the posterior is narrow and
its parameters differ in scale by orders of magnitude): the chains start
over-dispersed around the posterior's modes, found by L-BFGS, with each
mode's Laplace covariance as the proposal shape (:func:`start_chains`,
:mod:`latentforce.inference.laplace`); the proposal is adapted during the
warm-up only (:mod:`latentforce.inference.mcmc`); independence steps from
the modes' Laplace fit are mixed with the random walk
(:mod:`latentforce.inference.independence`); and ``iterations =
"auto"`` samples until R-hat and ESS say converged
(:func:`sample_in_chunks`, :mod:`latentforce.inference.convergence`).

Trajectories: the paper plots the smoother at one point estimate (the CDF
median), which ignores the parameter uncertainty. We report the honest
posterior of each state, mixed over posterior draws in bounded memory
(:mod:`latentforce.inference.mixture`).
"""

from __future__ import annotations

import functools
import time as _time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.compile import Bound, bound, jit, numbers
from latentforce.inference import independence, mcmc
from latentforce.inference.kalman import log_likelihood, log_likelihood_complete
from latentforce.inference.kalman_choice import (
    kalman_filter_for,
    rts_smoother_for,
    use_parallel,
)
from latentforce.inference.parallel_kalman import parallel_log_likelihood
from latentforce.models import LatentForceModel
from latentforce.priors import Prior, log_prob_coordinate, to_coordinate, to_value


class Initial(NamedTuple):
    """A user-given prior of the first state: mean and covariance (``[initial]``)."""

    mean: np.ndarray
    cov: np.ndarray


def initial_moments(model: LatentForceModel, params: dict, initial: Initial | None):
    """``(m0, P0)``: the user's ``[initial]`` section, else the model's default."""
    if initial is None:
        return model.default_initial(params)
    return jnp.asarray(initial.mean, dtype=float), jnp.asarray(initial.cov, dtype=float)


def linear_gaussian(model: LatentForceModel, params: dict, dt: float, initial: Initial | None = None):
    """The discrete linear-Gaussian model ``(A, Q, H, R, m0, P0)`` for ``params``."""
    A, Q = model.discretise(params, dt)
    H, R = model.observation(params)
    m0, P0 = initial_moments(model, params, initial)
    return A, Q, H, R, m0, P0


def smooth(
    model: LatentForceModel, params: dict, y, mask, dt: float, initial: Initial | None = None, kalman: str = "auto"
):
    """Exact smoothed moments and log-likelihood at fixed ``params`` (method ``kalman``).

    ``kalman``: which recursion (:mod:`latentforce.inference.kalman_choice`)."""
    A, Q, H, R, m0, P0 = linear_gaussian(model, params, dt, initial)
    T = np.shape(y)[0]
    filt = kalman_filter_for(kalman, T)(A, Q, H, R, m0, P0, jnp.asarray(y), jnp.asarray(mask))
    return rts_smoother_for(kalman, T)(A, filt)


def smooth_compiled(
    model: LatentForceModel, params: dict, y, mask, dt: float, initial: Initial | None = None, kalman: str = "auto"
):
    """:func:`smooth` as one compiled program per model structure and record shape (the numbers
    are its arguments); ``y`` where ``mask`` is False: anything finite or not."""
    return _smooth(*program_arguments(model, params, y, mask), initial, model=model, dt=float(dt), kalman=kalman)


def program_arguments(model: LatentForceModel, params: dict, y, mask) -> tuple:
    """``(numbers, y, mask)`` as a program compiled per model structure takes them: every parameter
    as a number (:meth:`LatentForceModel.complete`), ``y`` zero where not observed."""
    return numbers(model.complete(params)), jnp.asarray(np.where(mask, y, 0.0)), jnp.asarray(mask)


@functools.partial(jit, static_argnames=("model", "dt", "kalman"))
def _smooth(params: dict, y, mask, initial, *, model: LatentForceModel, dt: float, kalman: str):
    return smooth(model, params, y, mask, dt, initial, kalman)


def state_moments(model: LatentForceModel, means, covs):
    """Split smoothed moments into displacement / velocity (/ hysteretic force) / force (mean, sd)
    arrays."""
    var = jnp.diagonal(covs, axis1=-2, axis2=-1)
    out = {}
    for name in model.layout.states:
        idx = model.layout.index(name)
        out[name] = (means[..., idx], jnp.sqrt(jnp.clip(var[..., idx], 0.0)))
    return out


#: optimiser starts besides ``init`` (:func:`start_chains`)
N_DISPERSED_STARTS = 3
#: on records of at least 16x this many samples, the starts are explored on the first ones
#: (measured: at T = 5e4 the window's extra compile ate its gain; at 2e5 it saves ~10 s)
EXPLORE_WINDOW = 5000


class MCMCOutput(NamedTuple):
    """Raw output of :func:`run_kalman_mcmc` and :func:`~latentforce.inference.kalman_nuts.run_kalman_nuts`."""

    names: tuple[str, ...]
    draws: dict  # name -> (chains, iterations) physical values
    accepted: np.ndarray  # (chains, iterations); NUTS: mean acceptance statistic
    log_likelihood: np.ndarray  # (chains, iterations)
    acceptance: np.ndarray  # (chains,) post-warm-up acceptance rate
    proposal_scale: np.ndarray  # (chains,) adapted global scale (NUTS: step size)
    wall_time_s: float
    convergence: dict = {}  # latentforce.inference.convergence.diagnose record
    start: dict = {}  # how the chains were started: modes, optimiser record, seconds
    warmup: int = 0  # warm-up iterations per chain
    sampler_info: dict = {}  # method-specific extras (e.g. NUTS tree depth)


def log_posterior_fn(
    model: LatentForceModel,
    fixed: dict,
    names: tuple[str, ...],
    priors: tuple[Prior, ...],
    dt: float,
    initial: Initial | None = None,
    complete: bool = True,
    loglik: Callable | None = None,
    kalman: str = "auto",
) -> Bound:
    """``logpost(x, y, mask)`` of the unconstrained parameter vector ``x`` (data as arguments).

    ``loglik(params, y, mask)``, when given, replaces the exact Kalman
    log-likelihood (the ``ekf``/``ukf`` methods' approximate one).

    A :class:`~latentforce.compile.Bound`: the fixed values, the priors' numbers,
    the initial state and ``loglik``'s own numbers are its leaves, the model's
    structure, names and settings its static part, so records of one shape and
    configurations of one structure share one compiled sampler whatever their
    numbers. ``complete`` (every sample of
    every channel observed) selects the exact steady-state shortcut of
    :func:`~latentforce.inference.kalman.log_likelihood_complete`, unless
    ``kalman`` (:mod:`latentforce.inference.kalman_choice`) picks the parallel
    scan for the record's length, which serves every record.
    """
    static = (model, tuple(names), float(dt), bool(complete), kalman)
    return Bound(
        _logpost,
        static,
        (numbers(model.complete(fixed)), tuple(priors), initial, None if loglik is None else bound(loglik)),
    )


def _params_of(fixed: dict, names: tuple[str, ...], priors: tuple[Prior, ...], x) -> dict:
    params = dict(fixed)
    for i, name in enumerate(names):
        params[name] = to_value(priors[i], x[i])
    return params


def _coordinates(priors: tuple[Prior, ...], theta: np.ndarray) -> np.ndarray:
    """The samplers' coordinates of the values ``theta`` (last axis: the parameters)."""
    theta = np.asarray(theta, dtype=float)
    return np.stack([np.asarray(to_coordinate(p, theta[..., i])) for i, p in enumerate(priors)], axis=-1)


def _logpost(static, nums, x, y, mask):
    model, names, dt, complete, kalman = static
    fixed, priors, initial, loglik = nums
    params = _params_of(fixed, names, priors, x)
    if loglik is not None:
        ll = loglik(params, y, mask)
    else:
        lg = linear_gaussian(model, params, dt, initial)
        if use_parallel(kalman, y.shape[0]):  # decided at trace time, from the record's static length
            ll = parallel_log_likelihood(*lg, y, mask)
        else:
            ll = log_likelihood_complete(*lg, y) if complete else log_likelihood(*lg, y, mask)
    lp = sum(log_prob_coordinate(prior, x[i]) for i, prior in enumerate(priors))
    return lp + ll


def make_log_posterior(
    model: LatentForceModel,
    fixed: dict,
    names: tuple[str, ...],
    priors: tuple[Prior, ...],
    y,
    mask,
    dt: float,
    initial: Initial | None = None,
    kalman: str = "auto",
) -> tuple[Callable, Callable]:
    """Log posterior of the unconstrained parameter vector, and its log-likelihood part (data fixed)."""
    complete = bool(np.all(mask))
    y = jnp.asarray(np.where(mask, y, 0.0))
    mask = jnp.asarray(mask)
    logpost = log_posterior_fn(model, fixed, names, priors, dt, initial, complete, kalman=kalman)

    def loglik(x):
        return logpost(x, y, mask) - sum(log_prob_coordinate(p, x[i]) for i, p in enumerate(priors))

    return (lambda x: logpost(x, y, mask)), loglik


def start_chains(
    key,
    logpost: Callable,
    data: tuple,
    inits: np.ndarray,
    priors: tuple[Prior, ...],
    chains: int,
    *,
    use_modes: bool = True,
) -> tuple[np.ndarray, list[np.ndarray], dict, list]:
    r"""Chain starts ``(chains, p)``, each chain's proposal covariance, a record, and the modes.

    With ``use_modes`` (the default): the posterior's modes from L-BFGS
    started at ``init`` and at :data:`N_DISPERSED_STARTS` points dispersed around it
    (:func:`latentforce.inference.laplace.find_modes`); the chains start
    over-dispersed (twice the Laplace sd) around the modes that carry
    mass, each with its mode's Laplace covariance as its proposal shape.
    On a long record the starts are explored on its first
    :data:`EXPLORE_WINDOW` samples and only the optima found there are
    refined on the whole record.
    Without (or where the optimiser finds nothing finite), the paper's start:
    ``init`` times ``exp(0.3 z)`` and a 10 % diagonal step, and no modes.
    A signed parameter (:class:`latentforce.priors.SignedNormal`) is dispersed
    in its coordinate instead: by ``0.5 z`` (``0.3 z``) of its prior sd.
    """
    from latentforce.inference import laplace

    p = inits.size
    key_opt, key_start, key_old = jax.random.split(key, 3)
    x_init = _coordinates(priors, inits)
    signed = np.array([p.signed for p in priors], dtype=bool)

    def dispersed(z, scale):  # the starts x_init dispersed by exp(scale z) (signed: + scale z)
        return np.where(
            signed, x_init + scale * z, _coordinates(priors, np.where(signed, 1.0, inits) * np.exp(scale * z))
        )

    record: dict = {"method": "init"}
    if use_modes:
        t0 = _time.perf_counter()
        z = np.asarray(jax.random.normal(key_opt, (N_DISPERSED_STARTS, p)))
        # Dispersed in the physical value by a factor exp(0.5 z): at least an order of
        # magnitude over the starts, so a second mode of the likelihood can show itself.
        starts = np.concatenate([x_init[None], dispersed(z, 0.5)])
        T = data[0].shape[0]
        if T >= 16 * EXPLORE_WINDOW:
            # Explore from every start on the record's first samples (a cheaper, wider
            # posterior with the same modes), then refine each optimum found on the whole.
            window = tuple(a[:EXPLORE_WINDOW] for a in data)
            explored, opt_window = laplace.find_modes(logpost, starts, args=window)
            if explored:
                starts = np.stack([m.x for m in explored])
            modes, opt = laplace.find_modes(logpost, starts, args=data)
            opt = {"explore": dict(opt_window, samples=EXPLORE_WINDOW), "refine": opt}
        else:
            modes, opt = laplace.find_modes(logpost, starts, args=data)
        if modes:
            x0, which = laplace.chain_starts(key_start, modes, chains)
            record = {
                "method": "laplace",
                "optimiser": opt,
                "seconds": _time.perf_counter() - t0,
                "modes": [
                    {
                        "x": m.x.tolist(),
                        "log_posterior": m.log_posterior,
                        "log_mass": m.log_mass,
                        "laplace_ok": m.laplace_ok,
                        "sd": np.sqrt(np.diag(m.cov)).tolist(),
                    }
                    for m in modes
                ],
                "chain_mode": which.tolist(),
            }
            return x0, [modes[w].cov for w in which], record, modes
        record = {"method": "init", "optimiser": opt, "note": "the optimiser found no finite optimum"}
    z = np.asarray(jax.random.normal(key_old, (chains, p)))
    x0 = dispersed(z, 0.3) if chains > 1 else x_init[None, :]
    theta0 = np.stack([np.asarray(to_value(p, x0[:, i])) for i, p in enumerate(priors)], axis=-1)
    # A 10 % step in the physical value (or 0.1 in x where the value is below one; a signed
    # parameter: a tenth of its prior sd).
    sd0 = np.where(signed, 0.1, 0.1 * np.maximum(1.0, np.abs(theta0)))
    return x0, [np.diag(s**2) for s in sd0], record, []


def run_kalman_mcmc(
    key,
    model: LatentForceModel,
    fixed: dict,
    free: dict,
    y,
    mask,
    dt: float,
    *,
    iterations: int | None,
    burn_in: int,
    chains: int,
    initial: Initial | None = None,
    progress: Callable | None = None,
    chunk: int = 100,
    target_ess: float = 400,
    max_time: float = 600.0,
    use_modes: bool = True,
    adapt_shape: bool = True,
    loglik: Callable | None = None,
    checkpoint=None,
    kalman: str = "auto",
    independent: bool = True,
) -> MCMCOutput:
    """Random-walk Metropolis over the ``free`` parameters (Algorithm 1, ISMA 2018).

    ``free`` maps a parameter name to ``(prior, init)``; ``fixed`` holds the
    known values. Chains start as :func:`start_chains` says; the proposal is
    each chain's Laplace covariance scaled by :math:`2.38/\\sqrt p`, its
    scale adapted towards the optimal acceptance and its shape re-estimated
    from the chain (:mod:`latentforce.inference.mcmc`) during the
    ``burn_in`` warm-up only, then frozen. With ``independent`` (the
    default) and a mode found, independence steps from the modes' Laplace
    fit are mixed in (:mod:`latentforce.inference.independence`). ``iterations``: a number of
    draws per chain, or ``None`` for "auto": chunks of ``chunk`` draws until
    :func:`latentforce.inference.convergence.diagnose` says converged
    (``target_ess``) or ``max_time`` seconds have passed since the start.
    ``progress(done, total, acceptance)`` is called between chunks;
    ``checkpoint`` (:class:`latentforce.checkpoint.Checkpoint`) saves and
    restores the chunk loop (:func:`sample_in_chunks`).
    ``kalman``: which recursion computes the likelihood
    (:mod:`latentforce.inference.kalman_choice`).
    """
    t0 = _time.perf_counter()
    names = tuple(free)
    priors = tuple(free[n][0] for n in names)
    inits = np.array([float(free[n][1]) for n in names])
    complete = bool(np.all(mask))
    logpost = log_posterior_fn(model, fixed, names, priors, dt, initial, complete, loglik, kalman)
    data = (jnp.asarray(np.where(mask, y, 0.0)), jnp.asarray(mask))
    p = len(names)
    target = mcmc.target_acceptance(p)

    key_start, key_run = jax.random.split(key)
    x0, covs, start, modes = start_chains(key_start, logpost, data, inits, priors, chains, use_modes=use_modes)
    # Independence steps from the modes' Laplace fit (module doc), where the optimiser found a mode.
    proposal = independence.from_modes(modes) if (modes and independent) else None

    # The start's log density is left at -inf: the first proposal is then accepted
    # whatever it is (a warm-up step), which spares compiling a program just for it.
    covs = np.stack(covs)
    chols = np.stack([np.linalg.cholesky(c) for c in covs]) * (2.38 / np.sqrt(p))
    imh = (jnp.zeros(chains), jnp.zeros(chains)) if proposal is not None else (None, None)
    states = mcmc.RWMState(
        jnp.asarray(x0),
        jnp.full(chains, -jnp.inf),
        jnp.zeros(chains),
        jnp.asarray(chols),
        jnp.asarray(x0),
        jnp.asarray(covs),
        jnp.zeros(chains),
        *imh,
    )

    n_chunk = max(1, min(chunk, burn_in or chunk, iterations or chunk))
    burn_total = -(-burn_in // n_chunk) * n_chunk  # rounded up to whole chunks, never down
    # With a Laplace start the proposal already fits: re-shape it from the chain half-way
    # and at three quarters of the warm-up (from the paper's start, at each quarter).
    fractions = ((2, 3) if start["method"] == "laplace" else (1, 2, 3)) if adapt_shape else ()
    shape_at = tuple(sorted({f * burn_total // 4 for f in fractions} - {0}))

    def run_chunk(keys, s, start_step, adapt):
        s, xs, infos = _run_chains(
            logpost, keys, s, start_step, adapt, proposal, *data, n_chunk=n_chunk, shape_at=shape_at, target=target
        )
        stats = {"accepted": infos.accepted, "logdensity": infos.logdensity}
        if proposal is not None:
            stats["independent"] = infos.independent
        return s, xs, stats

    states, xs, stats, burn_total = sample_in_chunks(
        key_run,
        states,
        run_chunk,
        names,
        priors,
        chains=chains,
        n_chunk=n_chunk,
        burn_total=burn_total,
        iterations=iterations,
        target_ess=target_ess,
        max_time=max_time,
        t0=t0,
        progress=progress,
        checkpoint=checkpoint,
        sampler="kalman-mcmc",
    )
    accepted, lp = stats["accepted"], stats["logdensity"]
    draws, loglik, record = finish(xs, lp, names, priors, target_ess)
    info = {}
    if proposal is not None:
        ind = np.asarray(stats["independent"], dtype=bool)
        info["independence"] = {
            "modes": int(proposal.means.shape[0]),
            "probability": np.asarray(independence.choice_probability(states.imh_accept, states.imh_count)).tolist(),
            "share": ind.mean(axis=1).tolist(),
            "acceptance": [float(a[i].mean()) if i.any() else None for a, i in zip(accepted, ind)],
            "random_walk_acceptance": [float(a[~i].mean()) if (~i).any() else None for a, i in zip(accepted, ind)],
        }
    return MCMCOutput(
        names,
        draws,
        accepted,
        loglik,
        accepted.mean(axis=1),
        np.exp(np.asarray(states.log_scale)),
        _time.perf_counter() - t0,
        record,
        start,
        burn_total,
        info,
    )


@functools.partial(jit, static_argnames=("n_chunk", "shape_at", "target"))
def _run_chains(
    logpost: Bound, k, s, start_step, adapt, prop, y, mask, *, n_chunk: int, shape_at: tuple, target: float
):
    """``n_chunk`` iterations of every chain (vmapped): one compiled program per structure and shape."""

    def chain(kc, sc):
        return mcmc.run_chain(
            kc,
            sc,
            lambda x: logpost(x, y, mask),
            n_chunk,
            adapt=adapt,
            adapt_shape_at=shape_at,
            target=target,
            start=start_step,
            independent=prop,
        )

    return jax.vmap(chain)(k, s)


def sample_in_chunks(
    key,
    states,
    run_chunk: Callable,
    names: tuple[str, ...],
    priors: tuple[Prior, ...],
    *,
    chains: int,
    n_chunk: int,
    burn_total: int,
    iterations: int | None,
    target_ess: float,
    max_time: float,
    t0: float,
    progress: Callable | None = None,
    checkpoint=None,
    sampler: str = "kalman-mcmc",
):
    """Warm-up then sampling, in chunks of ``n_chunk`` iterations of one compiled program.

    ``run_chunk(keys, states, start_step, adapt) -> (states, xs (chains, n_chunk, p),
    stats {name: (chains, n_chunk)})``, with ``stats["accepted"]`` (for the
    progress line) and ``stats["logdensity"]`` (monitored beside the
    parameters). Fixed ``iterations`` are run (rounded up to whole chunks, the
    surplus dropped); ``None`` runs until converged or ``max_time``, and its warm-up
    stops at the first chunk's end after half of ``max_time``
    (:data:`~latentforce.inference.convergence.WARM_UP_SHARE`; not before
    :data:`~latentforce.inference.convergence.WARM_UP_FLOOR` of it has run), so that the
    draws get the other half: the adaptation stops there and the draws start.
    Returns the final states, the post-warm-up draws, their stats and the warm-up
    iterations run (``burn_total`` unless it was cut).

    The chunks' boundaries depend only on the settings and each chunk's keys
    only on ``key`` and the chunk's first iteration, so ``checkpoint`` (a
    :class:`latentforce.checkpoint.Checkpoint`, or None) is offered the loop
    state at every boundary, and a run restored from it continues exactly
    as the uninterrupted run (``states`` is then only the template of the
    restored chain states).
    """
    from latentforce.checkpoint import LoopState, tree_arrays, tree_from_arrays
    from latentforce.inference import convergence

    fixed_total = None if iterations is None else burn_total + -(-iterations // n_chunk) * n_chunk
    warm_up_cap = convergence.WARM_UP_SHARE * max_time if iterations is None else float("inf")
    done = 0
    xs_all: list = []
    stats_all: dict[str, list] = {}
    finished = False
    clock0 = t0  # max_time counts from here (moved back by a restored run's sampler time)
    saved = checkpoint.restore(sampler) if checkpoint is not None else None
    if saved is not None:
        done, finished = saved.done, saved.finished
        burn_total = int(saved.extra.get("warm_up", burn_total))
        states = tree_from_arrays(states, saved.arrays, "state")
        if "draws" in saved.arrays:
            xs_all = [saved.arrays["draws"]]
            stats_all = {k[len("stats/") :]: [v] for k, v in saved.arrays.items() if k.startswith("stats/")}
        clock0 = _time.perf_counter() - saved.elapsed_s
    run_keys = jax.random.split(key, chains)

    def loop_state() -> LoopState:
        arrays = tree_arrays("state", states)
        if xs_all:
            xs_all[:] = [np.concatenate(xs_all, axis=1)]
            arrays["draws"] = xs_all[0]
            for k, v in stats_all.items():
                v[:] = [np.concatenate(v, axis=1)]
                arrays[f"stats/{k}"] = v[0]
        return LoopState(done, finished, arrays, _time.perf_counter() - clock0, {"warm_up": burn_total})

    while not finished:
        adapt = done < burn_total
        keys = jax.vmap(lambda k: jax.random.fold_in(k, done))(run_keys)
        states, xs, stats = run_chunk(keys, states, done, adapt)
        if not adapt:
            xs_all.append(np.asarray(xs))
            for k, v in stats.items():
                stats_all.setdefault(k, []).append(np.asarray(v))
        done += n_chunk
        total = fixed_total if fixed_total is not None else max(done + n_chunk, burn_total + n_chunk)
        if progress is not None:
            progress(done, total, float(np.mean(np.asarray(stats["accepted"]))))
        if adapt:
            floor = convergence.WARM_UP_FLOOR * burn_total
            if floor <= done < burn_total and _time.perf_counter() - clock0 >= warm_up_cap:
                burn_total = done  # max_time: the warm-up ends here (the chunks' keys do not depend on it)
        elif fixed_total is not None:
            finished = done >= fixed_total
        else:
            # the verdict on what the run will report (finish): the physical values, whose folded
            # R-hat differs from the sampling coordinates' (2026-12-02, an ekf run with inferred
            # hyperparameters stopped "converged" in the sampling coordinates and reported R-hat 1.0104)
            draws = _physical(np.concatenate(xs_all, axis=1), names, priors)
            quantities = {**draws, "log_posterior": np.concatenate(stats_all["logdensity"], axis=1)}
            finished = (
                convergence.diagnose(quantities, target_ess=target_ess)["converged"]
                or _time.perf_counter() - clock0 >= max_time
            )
        if checkpoint is not None:
            checkpoint.save(sampler, loop_state)
    n_kept = iterations if iterations is not None else done - burn_total
    xs = np.concatenate(xs_all, axis=1)[:, :n_kept]
    return states, xs, {k: np.concatenate(v, axis=1)[:, :n_kept] for k, v in stats_all.items()}, burn_total


def finish(
    xs: np.ndarray, logpost: np.ndarray, names: tuple[str, ...], priors: tuple[Prior, ...], target_ess: float
) -> tuple[dict, np.ndarray, dict]:
    """Physical draws, the log-likelihood of each draw, and the convergence record."""
    from latentforce.inference import convergence

    # The log-likelihood part of each draw: log posterior minus log prior (cheap, exact).
    log_prior = sum(np.asarray(log_prob_coordinate(prior, jnp.asarray(xs[..., i]))) for i, prior in enumerate(priors))
    draws = _physical(xs, names, priors)
    quantities = {**draws, "log_posterior": logpost}
    return draws, logpost - log_prior, convergence.diagnose(quantities, target_ess=target_ess)


def _physical(xs: np.ndarray, names: tuple[str, ...], priors: tuple[Prior, ...]) -> dict[str, np.ndarray]:
    """The draws ``xs`` (chains, draws, p) in the sampling coordinates as physical values by name."""
    return {n: np.asarray(to_value(priors[i], jnp.asarray(xs[..., i]))) for i, n in enumerate(names)}
