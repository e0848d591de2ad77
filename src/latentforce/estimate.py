"""The main job: a validated problem and its measured data in, a posterior out.

Dispatches on ``[inference].method`` to the inference modules and packs
their output into a :class:`latentforce.results.RunResult`. No file I/O
and no printing here: the CLI reads the inputs and writes the result
folder; progress goes through an optional callback.
"""

from __future__ import annotations

import time as _time
from typing import Callable

import jax
import numpy as np

from latentforce import latent_grid, run_checks, substeps
from latentforce.compile import call, numbers, require_x64
from latentforce.errors import LatentForceError
from latentforce.estimate_particles import (  # noqa: F401
    PGAS_AUTO_ITERATIONS,
    _mechanical_initial,
    _run_pgas,
    gaussian_for,
    softening_hint,
)
from latentforce.inference.kalman_mcmc import Initial, run_kalman_mcmc, smooth_compiled, state_moments
from latentforce.inference.smoother_draws import gaussian_paths, kalman_paths
from latentforce.io.channels import channel_units, noise_in_si
from latentforce.io.config import Problem
from latentforce.io.data import Dataset
from latentforce.io.units import override_warning
from latentforce.outputs import gaussian_moments, output_matrix
from latentforce.outputs import split as split_outputs
from latentforce.outputs import units as output_units
from latentforce.results import RunResult, summarise_parameters
from latentforce.spectrum import force_spectrum
from latentforce.systems import linearised_stability


def _truth(model, dataset: Dataset) -> dict[str, np.ndarray]:
    """Truth columns of the data file as ``(T, width)`` arrays, where complete."""
    out = {}
    for name in model.layout.states:
        width = len(model.layout.index(name))
        keys = [name] if width == 1 else [f"{name}_{j}" for j in range(width)]
        if all(k in dataset.truth for k in keys):
            out[name] = np.stack([np.asarray(dataset.truth[k], dtype=float) for k in keys], axis=1)
    return out


def _check_stable(problem: Problem, params: dict) -> None:
    """The default initial state is the stationary distribution of the system (linear) or of
    its linearisation about rest (nonlinear): it exists only for a stable one."""
    model = problem.model
    if problem.initial is not None:
        return
    # the linear part's (z, zdot) dynamics (internal states follow r = R_z z there, models.py)
    eig, stable = linearised_stability(model.system, numbers(params))
    if not stable:
        what = "linear system" if model.system.is_linear else "system, linearised about rest,"
        raise LatentForceError(
            f"The {what} in {problem.config_path} is not asymptotically stable (an eigenvalue "
            f"of its state matrix has real part {np.max(eig.real):.3g}, zero or positive up to round-off: is "
            "the damping zero or the "
            "stiffness singular or negative?), so its stationary distribution, the default initial state, "
            "does not exist. Add damping, or give the initial state explicitly in an [initial] section "
            "with mean and sd."
        )


def run(
    problem: Problem,
    dataset: Dataset,
    *,
    seed: int | None = None,
    progress: Callable | None = None,
    channels=None,
    checkpoint=None,
) -> tuple[RunResult, dict]:
    """Run the configured inference; returns the result and method-specific extras.

    ``channels`` (``pgas`` only): ``(quantity, dof)`` pairs through which the
    sampler observes the system, a superset of the sensors'; runs that differ
    only in their sensors then share their compiled programs
    (:func:`latentforce.inference.pgas.observe_through`). The posterior is the
    same (the draws too, except as that function's caller, ``run_pgas``, says).

    ``extras`` holds what a demo may want beyond the result folder, e.g. the
    smoother at the point estimate for ``kalman-mcmc``.

    ``checkpoint`` (:class:`latentforce.checkpoint.Checkpoint`, sampling
    methods): the sampler saves its chunk loop there and, where it holds a
    saved one, continues from it; the result is then the uninterrupted run's
    (the post-processing is rerun), with ``diagnostics["resumed"]`` added.
    """
    require_x64("latentforce.estimate.run")
    result, extras = _run(problem, dataset, seed, progress, channels, checkpoint)
    elements = getattr(problem.model.system, "elements", ())
    if elements:  # an MDOF structure's nonlinear elements, in order (the hysteresis figure reads them)
        result.diagnostics["elements"] = [{"type": e.kind, "dofs": list(e.dofs)} for e in elements]
    if problem.carried:
        result.diagnostics["carried_priors"] = problem.carried
        for key, c in problem.carried.items():
            if c["converged"] is False:
                result.diagnostics.setdefault("warnings", []).append(
                    f"the prior of {key} is carried from {c['from']}, whose run did not converge: its "
                    "posterior, and so this prior, may be wrong or too narrow. Rerun that calibration to "
                    "convergence first."
                )
    return result, extras


def _run(
    problem: Problem, dataset: Dataset, seed: int | None, progress: Callable | None, channels, checkpoint
) -> tuple[RunResult, dict]:
    t0 = _time.perf_counter()
    # The data are in SI (io/channels.py); each sensor's noise_std, in its channel's unit, follows.
    problem = noise_in_si(problem, dataset)
    model = problem.model
    settings = problem.inference
    seed = settings.seed if seed is None else seed
    key = jax.random.key(seed)
    initial = None if problem.initial is None else Initial(*problem.initial)
    params0 = dict(problem.fixed)
    for name, spec in problem.free.items():
        params0[name] = spec.init
    _check_stable(problem, params0)
    # the nonlinear methods' model steps per sample (latent_grid): the run sees the record on that grid
    problem, grid, steps, grid_record = latent_grid.for_problem(problem, params0, dataset)
    problem, substeps_warning = substeps.for_problem(problem, params0, grid.dt)
    fixed_record = {k: (float(v) if np.ndim(v) == 0 else np.asarray(v).tolist()) for k, v in problem.fixed.items()}

    def shared(ds: Dataset) -> dict:
        mask_ = np.asarray(ds.mask, dtype=bool)
        return dict(
            time=np.asarray(ds.time),
            ndof=model.ndof,
            nforce=model.nforce,
            observed={c: np.where(mask_[:, i], ds.values[:, i], np.nan) for i, c in enumerate(ds.columns)},
            truth=_truth(model, ds),
            seed=seed,
            fixed=fixed_record,
            units=channel_units(ds),
            outputs=output_units(problem.outputs),
        )

    common = shared(dataset)
    common_grid = common if grid is dataset else shared(grid)
    y_grid, mask_grid = np.asarray(grid.values, dtype=float), np.asarray(grid.mask, dtype=bool)
    start_check, motion_warning = run_checks.start_in_motion(problem, params0, y_grid, mask_grid, grid.time)
    result, extras = _dispatch(
        key, problem, grid, params0, y_grid, mask_grid, initial, common_grid, progress, t0, channels, checkpoint
    )
    rerun, recheck_warning = substeps.recheck(problem, result, grid.dt)
    if rerun is not None:  # once: the count is then chosen at the posterior the data give
        getattr(progress, "close", lambda: None)()  # the rerun's bar starts anew
        used = int(problem.model.system.substeps)
        try:
            # not checkpointed: a run killed here resumes the first pass's finished loop and reruns this
            second = _dispatch(
                key, rerun, grid, params0, y_grid, mask_grid, initial, common_grid, progress, t0, channels, None
            )
        except Exception as err:  # noqa: BLE001 - the first pass is the user's result; say why it stands
            failed = f"chosen at the init values; the rerun at its need failed ({type(err).__name__}: {err})"
            _, recheck_warning = substeps.recheck(problem, result, grid.dt, rerun=False, reason=failed)
        else:
            problem = rerun
            result, extras = second
            result.diagnostics["substeps_first_pass"] = used
            _, recheck_warning = substeps.recheck(problem, result, grid.dt, rerun=False)
            result.diagnostics.setdefault("warnings", []).append(
                f"the run was made twice: its first pass's posterior reached parameters where the structure's "
                f"rate needs more than the {used} RK4 substeps a sample chosen at the init values, so it was "
                f"rerun with {int(problem.model.system.substeps)} (reported here; each pass had its own "
                "max_time). Give [system].substeps to fix the count and run once."
            )
    result = latent_grid.on_samples(result, steps, common)
    if steps > 1 and "median_smoother" in extras:  # ekf/ukf with inferred parameters
        extras["median_smoother"] = {n: (m[::steps], s[::steps]) for n, (m, s) in extras["median_smoother"].items()}
    if grid_record is not None:
        result.diagnostics["steps_per_sample"] = steps
        result.diagnostics["grid_check"] = grid_record
    unit_warning = override_warning(getattr(dataset, "units", None))
    notes = (*problem.notes, *getattr(dataset, "notes", ()))
    if start_check is not None:
        result.diagnostics["start_check"] = start_check
    warnings_ = (motion_warning, unit_warning, substeps_warning, recheck_warning, latent_grid.warning(grid_record))
    for warning in (*notes, *warnings_):
        if warning:
            result.diagnostics.setdefault("warnings", []).append(warning)
    if not problem.model.system.is_linear:
        result.diagnostics["substeps"] = int(problem.model.system.substeps)
    run_checks.mass_warning(problem, result)
    run_checks.weak_identification_warning(problem, result)
    run_checks.start_warning(result)
    run_checks.gaussian_approximation_warning(problem, result)
    run_checks.sampling_rate_warning(problem, params0, dataset.dt, result)
    result.force_psd = force_spectrum(problem, result, params0, dataset.dt)
    return result, extras


def _dispatch(
    key,
    problem: Problem,
    dataset: Dataset,
    params0: dict,
    y,
    mask,
    initial,
    common: dict,
    progress,
    t0: float,
    channels,
    checkpoint=None,
) -> tuple[RunResult, dict]:
    """The configured method's result (:func:`run` adds what every method shares)."""
    model = problem.model
    settings = problem.inference
    extras: dict = {}

    if settings.method == "kalman":
        sm = smooth_compiled(model, params0, y, mask, dataset.dt, initial, kalman=settings.kalman)
        if not np.isfinite(float(sm.log_likelihood)):
            raise LatentForceError(
                "The Kalman filter's log-likelihood is not finite for the configured "
                f"model in {problem.config_path}: check the parameter values and units."
            )
        state_mean, state_sd = _smoothed_moments(problem, params0, sm.means, sm.covs)
        from latentforce.inference import fit_check

        errors = fit_check.prediction_errors(model, params0, y, mask, dataset.dt, initial)
        diagnostics = {"prediction_errors": errors}
        message = fit_check.warning(errors)
        if message:
            diagnostics["warnings"] = [message]
        result = RunResult(
            method="kalman",
            diagnostics=diagnostics,
            state_mean=state_mean,
            state_sd=state_sd,
            param_draws={},
            path_draws=kalman_paths(
                key, model, params0, y, mask, dataset.dt, initial, problem.outputs, settings.kalman
            ),
            sample_stats={},
            acceptance=[],
            log_likelihood=float(sm.log_likelihood),
            wall_time_s=_time.perf_counter() - t0,
            **common,
        )
        return result, extras

    if settings.method in ("kalman-mcmc", "kalman-nuts"):
        result = _run_kalman_sampler(key, problem, dataset, y, mask, initial, common, progress, t0, extras, checkpoint)
        return _resumed(result, checkpoint), extras

    if settings.method in ("ekf", "ukf"):
        result = _run_gaussian(key, problem, dataset, params0, y, mask, common, progress, t0, extras, checkpoint)
        return _resumed(result, checkpoint), extras

    if settings.method == "pgas":
        result = _run_pgas(key, problem, dataset, params0, y, mask, common, progress, t0, channels, checkpoint)
        return _resumed(result, checkpoint), extras

    raise LatentForceError(f"Unknown inference method {settings.method!r}.")  # config validates this


def _smoothed_moments(problem: Problem, params: dict, means, covs, outputs=None) -> tuple[dict, dict]:
    r"""Per-state posterior means and sds of a Gaussian smoother (``kalman``, ``ekf``, ``ukf`` at fixed
    parameters), the ``[[outputs]]`` included: :math:`G m_t` and :math:`\operatorname{diag}(G P_t G^T)`
    from the full covariances, or ``outputs = (means, variances)`` where the smoother gave them
    (``ekf``/``ukf``, any system: its own transform)."""
    mom = state_moments(problem.model, means, covs)
    state_mean = {k: np.asarray(v[0]) for k, v in mom.items()}
    state_sd = {k: np.asarray(v[1]) for k, v in mom.items()}
    if problem.outputs:
        if outputs is None:
            G = output_matrix(problem.model, problem.outputs, params)
            moments = gaussian_moments(G, means, covs)
        else:
            moments = (np.asarray(outputs[0]), np.sqrt(np.asarray(outputs[1])))
        out_mean, out_sd, _ = split_outputs(problem.outputs, *moments)
        state_mean.update(out_mean)
        state_sd.update(out_sd)
    return state_mean, state_sd


def _run_gaussian(
    key,
    problem: Problem,
    dataset: Dataset,
    params0: dict,
    y,
    mask,
    common: dict,
    progress,
    t0: float,
    extras: dict,
    checkpoint=None,
) -> RunResult:
    """``ekf`` / ``ukf``: the Gaussian smoother at fixed parameters, or random-walk Metropolis over the
    inferred ones on its approximate likelihood with the states mixed over the draws."""
    settings = problem.inference
    loglik, smoother = gaussian_for(problem, params0, dataset.dt, outputs=problem.outputs)
    if problem.free:
        return _run_kalman_sampler(
            key, problem, dataset, y, mask, None, common, progress, t0, extras, checkpoint, gaussian=(loglik, smoother)
        )
    y0 = np.where(mask, y, 0.0)
    sm = call(smoother, numbers(params0), y0, mask)
    if not np.isfinite(float(sm.log_likelihood)):
        t = int(sm.first_nonfinite)
        where = f" (the filter overflowed at sample {t}, t = {dataset.time[t]:.6g} s)" if t >= 0 else ""
        raise LatentForceError(
            f"The {settings.method.upper()} log-likelihood is not finite for the configured "
            f"model in {problem.config_path}{where}: check the parameter values and units"
            f"{softening_hint(params0)}. Nothing was written."
        )
    state_mean, state_sd = _smoothed_moments(problem, params0, sm.means, sm.covs, (sm.output_means, sm.output_vars))
    bad = [n for n in state_mean if not (np.all(np.isfinite(state_mean[n])) and np.all(np.isfinite(state_sd[n])))]
    if bad:
        raise LatentForceError(
            f"The {settings.method.upper()} smoother broke down numerically on {problem.config_path}: "
            f"its posterior of {', '.join(bad)} is not finite (NaN or inf) although its log-likelihood "
            f"is. Nothing was written. A smooth force kernel with a short lengthscale against the sample "
            f"interval makes the smoother's covariances very ill-conditioned: try a lower Matérn order "
            f'or method = "pgas".'
        )
    return RunResult(
        method=settings.method,
        state_mean=state_mean,
        state_sd=state_sd,
        param_draws={},
        path_draws=gaussian_paths(key, problem.model, smoother, params0, y, mask, problem.outputs),
        sample_stats={},
        acceptance=[],
        log_likelihood=float(sm.log_likelihood),
        convergence={
            "converged": True,
            "exact": False,
            "note": f"{settings.method}: a deterministic Gaussian approximation (no sampling error); "
            "for a nonlinear system its bands may be too narrow",
        },
        diagnostics={"discretisation": settings.discretisation},
        wall_time_s=_time.perf_counter() - t0,
        **common,
    )


def _laplace_evidence(problem: Problem, modes: list[dict]) -> dict:
    r"""The Laplace estimate of the log evidence :math:`\log p(y)` (the model's, the parameters
    integrated out under their priors): the log-sum over the optimiser's modes of each one's
    Laplace mass. Comparable between runs on the same data with different kernels (or systems,
    or sensors' noise models); a higher value is the model the data favour. Undefined under a
    flat (improper) prior, whose normalising constant is arbitrary."""
    from latentforce.priors import Flat

    flat = [n for n, spec in problem.free.items() if isinstance(spec.prior, Flat)]
    if flat:
        return {
            "laplace": None,
            "reason": f"flat (improper) prior on {', '.join(flat)}: the evidence is "
            "defined only up to an arbitrary constant",
        }
    masses = [m["log_mass"] for m in modes if m.get("laplace_ok") and np.isfinite(m.get("log_mass", np.nan))]
    if not masses:
        return {"laplace": None, "reason": "no mode with a positive definite Laplace fit"}
    top = max(masses)
    return {"laplace": float(top + np.log(np.sum(np.exp(np.asarray(masses) - top)))), "modes": len(masses)}


def _resumed(result: RunResult, checkpoint) -> RunResult:
    """Record in the diagnostics where a resumed run took over (its draws are the uninterrupted run's)."""
    if checkpoint is not None and checkpoint.resumed_from is not None:
        result.diagnostics["resumed"] = dict(checkpoint.resumed_from)
    return result


def _run_kalman_sampler(
    key,
    problem: Problem,
    dataset: Dataset,
    y,
    mask,
    initial,
    common: dict,
    progress,
    t0: float,
    extras: dict,
    checkpoint=None,
    gaussian=None,
) -> RunResult:
    """``kalman-mcmc`` or ``kalman-nuts``: parameter draws, then the states mixed over them
    (``gaussian = (loglik, smoother)``: ``ekf``/``ukf`` with random-walk Metropolis)."""
    from latentforce.inference import convergence
    from latentforce.inference.kalman_nuts import run_kalman_nuts
    from latentforce.inference.mixture import mixture_posterior

    model = problem.model
    settings = problem.inference
    key_mcmc, key_mix = jax.random.split(key)
    free = {n: (spec.prior, spec.init) for n, spec in problem.free.items()}
    runner = run_kalman_nuts if settings.method == "kalman-nuts" else run_kalman_mcmc
    loglik, smoother = gaussian if gaussian is not None else (None, None)
    out = runner(
        key_mcmc,
        model,
        dict(problem.fixed),
        free,
        y,
        mask,
        dataset.dt,
        iterations=settings.iterations,
        burn_in=settings.burn_in,
        chains=settings.chains,
        initial=initial,
        progress=progress,
        target_ess=settings.target_ess,
        max_time=settings.max_time,
        checkpoint=checkpoint,
        kalman=settings.kalman,
        **({"loglik": loglik} if loglik is not None else {}),
    )
    pooled = {n: d.reshape(-1) for n, d in out.draws.items()}
    point = {f"{n}_mean": float(np.mean(v)) for n, v in pooled.items()}
    point.update({f"{n}_median": float(np.median(v)) for n, v in pooled.items()})
    # The paper's estimate: the smoother at the CDF median of each parameter.
    median = {n: float(np.median(v)) for n, v in pooled.items()}
    mix = mixture_posterior(
        key_mix,
        model,
        dict(problem.fixed),
        out.draws,
        y,
        mask,
        dataset.dt,
        thin_draws=settings.thin_draws,
        initial=initial,
        point=median,
        outputs=problem.outputs,
        smoother=smoother,
        kalman=settings.kalman,
    )
    mom_median, ll_median = mix.point
    extras["median_smoother"] = mom_median
    n_draws = next(iter(out.draws.values())).shape[1]
    diagnostics = {
        "proposal_scale": out.proposal_scale.tolist(),
        "sampler_wall_time_s": out.wall_time_s,
        "iterations": "auto" if settings.iterations is None else settings.iterations,
        "draws_per_chain": int(n_draws),
        "burn_in": settings.burn_in,
        "warmup": out.warmup,
        "chains": settings.chains,
        "mixture_draws": mix.n_mix,
        "start": out.start,
        **out.sampler_info,
    }
    modes = out.start.get("modes", [])
    diagnostics["log_evidence"] = _laplace_evidence(problem, modes)
    record = dict(out.convergence)
    # The states are exact given the parameters: their stored paths' R-hat is information only.
    states = convergence.state_quantities(
        {k: mix.paths[k] for k in problem.model.layout.states},
        convergence.monitored_times(len(dataset.time)),
        np.asarray(dataset.time),
    )
    if mix.paths["force"].shape[1] >= 4 and settings.chains >= 2:
        record["states"] = convergence.diagnose({}, states, states_decide=False)["states"]
    warnings_ = []
    strong = [m for m in modes if m["log_mass"] >= modes[0]["log_mass"] - 10.0] if modes else []
    if len(strong) > 1:
        warnings_.append(
            f"the posterior has {len(strong)} modes of comparable mass (found by the optimiser from "
            "dispersed starts; see diagnostics.start.modes): the chains were started in each, and the "
            "parameter and force estimates are a mixture over them (as in §6 of the ISMA 2018 paper)."
        )
    message = convergence.warning_message(record, settings.method, softening_hint({**problem.fixed, **out.draws}))
    if message:
        warnings_.append(message)
    cut = convergence.warm_up_cut_warning(settings.burn_in, out.warmup, settings.max_time)
    if cut:  # only "auto" runs are cut
        warnings_.append(cut)
    if warnings_:
        diagnostics["warnings"] = warnings_
    truth = common["truth"]
    if truth:
        from latentforce.results import by_column, coverage, nmse

        median = {k: m for k, (m, _) in mom_median.items()}
        diagnostics["nmse_median_smoother"] = by_column(nmse, truth, median)
        means, sds = ({k: v[j] for k, v in mix.moments.items()} for j in (0, 1))
        diagnostics["coverage_3sd"] = by_column(coverage, truth, means, sds)
    # Parameters at the same iterations as the trajectories, so both share (chain, draw).
    return RunResult(
        method=settings.method,
        state_mean={k: m for k, (m, _) in mix.moments.items()},
        state_sd={k: s for k, (_, s) in mix.moments.items()},
        param_draws={n: d[:, mix.path_index] for n, d in out.draws.items()},
        path_draws=mix.paths,
        sample_stats={"accepted": out.accepted.astype(float), "log_likelihood": out.log_likelihood},
        acceptance=out.acceptance.tolist(),
        log_likelihood=ll_median,
        point_estimate=point,
        diagnostics=diagnostics,
        param_summary=summarise_parameters(out.draws),
        param_chains={n: np.asarray(d) for n, d in out.draws.items()},
        convergence=record,
        wall_time_s=_time.perf_counter() - t0,
        **common,
    )
