"""Checks a run makes of the user's model and data, each adding a warning to the result's diagnostics
where it finds something a user should know: a mass traded against the force, a parameter the data
barely identify, a sampler's start that found no mode, natural frequencies past the Nyquist frequency,
a nonlinear record that starts in motion against the default near-rest start, and the Gaussian
approximation of ``ekf``/``ukf`` on a nonlinear system."""

from __future__ import annotations

import jax
import numpy as np

from latentforce.compile import numbers
from latentforce.io.config import Problem
from latentforce.results import RunResult


def mass_warning(problem: Problem, result: RunResult) -> None:
    """Force and mass trade off (``u/m`` is what motion sensors see): inferring a mass
    without a load cell leans on its prior alone for the scale of the force. A mass whose prior
    is carried from an earlier run (``prior = "posterior"``, e.g. a calibration with a load cell)
    is that run's identification: no warning."""
    carried = set()
    for key in problem.carried or {}:  # "[system].m", "[system].masses[2]"
        tail = key.rsplit(".", 1)[-1]
        carried.add("m_" + tail[len("masses[") : -1] if tail.startswith("masses[") else tail)
    masses = [n for n in problem.free if (n == "m" or (n.startswith("m_") and n[2:].isdigit())) and n not in carried]
    if masses and not any(s.quantity == "force" for s in problem.model.sensors):
        result.diagnostics.setdefault("warnings", []).append(
            f"the mass ({', '.join(masses)}) is inferred but no sensor measures the force "
            '(quantity = "force"): with only motion measured, force and mass trade off (a force '
            "twice as large on a mass twice as large gives much the same response), so the mass and "
            "the force's scale are set by their priors. Add a load cell channel to identify the mass."
        )


def start_failed(start: dict | None) -> bool:
    """Whether a sampler's start (``diagnostics.start``) searched for the posterior's mode and found no
    definite maximum: ``pgas``'s filter mode (``laplace_ok``), or the Kalman samplers' optimiser (no
    finite optimum, or no mode with a negative definite Hessian)."""
    if not start:
        return False
    if "laplace_ok" in start:  # pgas (pgas_mode.mode_start)
        return not start["laplace_ok"]
    if start.get("method") == "laplace":
        return not any(m.get("laplace_ok") for m in start.get("modes", []))
    return "optimiser" in start  # searched, and fell back to the init values


def start_warning(result: RunResult) -> None:
    """An unconverged run whose start found no definite mode: say so, since the chains then began at
    the best point reached with a generic proposal shape, and the usual cure is the model's, not time."""
    if (result.convergence or {}).get("converged", True) or not start_failed(result.diagnostics.get("start")):
        return
    result.diagnostics.setdefault("warnings", []).append(
        "the start's search for the posterior's mode found no definite maximum (diagnostics.start: the "
        "log posterior's Hessian at the best point reached is not negative definite, or no finite optimum "
        "was found), so the chains began there with a generic proposal shape. A parameter the data do not "
        "constrain (a flat prior on it, or no sensor that sees it) or an init far from the data's values "
        "does this: give it a proper prior or an init nearer the truth, or fix it."
    )


def natural_frequencies(problem: Problem, params: dict) -> np.ndarray:
    """The structure's natural frequencies (Hz) at ``params``, linearised about rest: the
    oscillatory eigenvalues of its mechanical state matrix, ``|lambda| / 2 pi``."""
    model = problem.model
    F, _ = model.continuous(numbers(params), linear_part=True)
    mech = model.layout.mech
    lam = np.linalg.eigvals(np.asarray(F, dtype=float)[mech, mech])
    return np.sort(np.abs(lam[np.abs(lam.imag) > 1e-9 * np.abs(lam)]) / (2 * np.pi))


def sampling_rate_warning(problem: Problem, params: dict, dt: float, result: RunResult) -> None:
    """A structure whose natural frequency is above the data's Nyquist frequency: the sample rate
    or the time column's unit is likely wrong (time in ms gave finite, meaningless answers)."""
    try:
        freqs = natural_frequencies(problem, params)
    except (TypeError, ValueError, np.linalg.LinAlgError):
        return
    nyquist = 0.5 / dt
    above = freqs[freqs > nyquist]
    if above.size:
        result.diagnostics.setdefault("warnings", []).append(
            f"the structure's natural frequencies {', '.join(f'{f:.4g}' for f in np.unique(above.round(6)))} Hz "
            f"(at the parameters' fixed or init values) are above the data's Nyquist frequency, "
            f"{nyquist:.4g} Hz (a time step of {dt:.4g} s): the record cannot resolve those modes, and the "
            "force and states at those frequencies are aliased. Check [data].sample_rate, or that the time "
            "column is in seconds (not milliseconds), and the system's masses and stiffnesses."
        )


#: A posterior whose sd (in the samplers' softplus space) is at least this share of its
#: prior's: the data carry at most ~36 % of its precision (1 - 0.8^2), the prior the rest.
WEAK_SD_RATIO = 0.8


def weak_identification_warning(problem: Problem, result: RunResult) -> None:
    """Name every sampled parameter whose posterior is barely narrower than its (proper) prior."""
    from latentforce.priors import Flat, to_coordinate

    weak = []
    for i, (name, spec) in enumerate(problem.free.items()):
        draws = result.param_draws.get(name)
        if draws is None or isinstance(spec.prior, Flat) or np.size(draws) < 20:
            continue
        sample = spec.prior.sample(jax.random.fold_in(jax.random.key(7), i), (4000,))
        prior = np.asarray(to_coordinate(spec.prior, sample))
        post = np.asarray(to_coordinate(spec.prior, np.asarray(draws, dtype=float)))
        post = post.reshape(-1, post.shape[-1]) if post.ndim > 1 else post[None]
        ok = np.isfinite(prior)
        # the sd within chains: chains stuck apart (not converged, reported as such) would make the
        # pooled sd many times the prior's (measured: 83x on a frame whose chains disagreed, R-hat 3.2)
        within = float(np.sqrt(np.mean(np.var(post, axis=1))))
        ratio = within / float(np.std(prior[ok])) if ok.sum() > 100 else float("nan")
        if np.isfinite(ratio) and ratio >= WEAK_SD_RATIO:
            weak.append(f"{name} (posterior sd {ratio:.2f} of the prior's)")
    if weak:
        result.diagnostics.setdefault("warnings", []).append(
            f"weakly identified: {', '.join(weak)}, in the samplers' space (softplus^-1 of the value; "
            "a parameter of either sign: its value). "
            "The data say little about them: their posteriors are mostly their priors, and so is what "
            "depends on them. Fix them at known values, narrow their priors from other evidence, or add a "
            "sensor that sees them."
        )


#: the first window's mean normalised innovation squared (per observed channel) above which, and above
#: :data:`START_RATIO` times the record's median window, a nonlinear record is taken to start in motion
START_LIMIT = 4.0
START_RATIO = 4.0


def innovation_windows(nis, nobs, width: int) -> np.ndarray:
    """Mean normalised innovation squared per observed channel over consecutive windows of ``width``
    steps (1 where the filter's Gaussian is right; NaN for a window without observations)."""
    nis, nobs = np.asarray(nis, dtype=float), np.asarray(nobs, dtype=float)
    n = max(1, len(nis) // width)
    sums = np.add.reduceat(nis[: n * width], np.arange(0, n * width, width))
    counts = np.add.reduceat(nobs[: n * width], np.arange(0, n * width, width))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / counts, np.nan)


def start_window(problem: Problem, params: dict, dt: float, T: int) -> int:
    """Steps in one period of the structure's lowest natural frequency (linearised about rest at
    ``params``), at least 10 and at most a quarter of the record: how long a wrong start takes to show
    in the predictions and to be corrected by the data."""
    try:
        freqs = natural_frequencies(problem, params)
    except (TypeError, ValueError, np.linalg.LinAlgError):
        freqs = np.zeros(0)
    width = round(1.0 / (float(freqs[0]) * dt)) if freqs.size and freqs[0] > 0 else T // 20
    return int(min(max(10, width), max(10, T // 4)))


def start_in_motion(problem: Problem, params: dict, y, mask, time) -> tuple[dict | None, str | None]:
    """``(record, warning)``: does a nonlinear record seem to start in motion, against the default prior
    of its first state (near rest, :meth:`latentforce.models.LatentForceModel.default_initial`)? The
    extended Kalman filter from that prior at ``params``: where its one-step predictions over the first
    period (:func:`start_window`) miss the data by far more than their predicted spread, and far more
    than over the rest of the record, the start is the misfit (a record cut from motion), not the model.
    ``(None, None)`` where it does not apply: a linear system (its default start is stationary), an
    ``[initial]`` given, a method other than ``pgas``/``ekf``/``ukf``, or a record shorter than two windows."""
    model, method = problem.model, problem.inference.method
    if model.system.is_linear or problem.initial is not None or method not in ("pgas", "ekf", "ukf"):
        return None, None
    from latentforce.compile import call
    from latentforce.estimate_particles import gaussian_for
    from latentforce.inference.gaussian import innovations_of

    time = np.asarray(time, dtype=float)
    dt = float(time[1] - time[0])
    width = start_window(problem, params, dt, len(time))
    if len(time) < 2 * width:
        return None, None
    loglik, _ = gaussian_for(problem, params, dt, "ekf")
    y0 = np.where(mask, y, 0.0)
    nis = np.asarray(call(innovations_of(loglik), numbers(params), y0, np.asarray(mask, dtype=bool)))
    nobs = np.sum(mask, axis=1)
    windows = innovation_windows(nis, nobs, width)
    first, rest = windows[0], np.nanmedian(windows[1:]) if np.any(np.isfinite(windows[1:])) else np.nan
    # where in the first window the misfit is largest: a record cut from motion misfits over much of it
    # (the filter's near-rest belief is contradicted for tens of samples, 2026-12-04 probe); an impact
    # far beyond the force prior (the same warning) at the time of the blow, for a sample or two
    peak = int(np.argmax(np.where(nobs[:width] > 0, nis[:width] / np.maximum(nobs[:width], 1), -np.inf)))
    record = {
        "window_s": width * dt,
        "first": float(first),
        "median_rest": float(rest),
        "peak_s": float(time[peak] - time[0]),
    }
    if not (np.isfinite(first) and np.isfinite(rest)) or first <= max(START_LIMIT, START_RATIO * rest):
        return record, None
    return record, (
        f"the record seems to start in motion: over its first {width * dt:.3g} s (one period of the structure) "
        f"the data miss the one-step predictions of the extended Kalman filter, started from the default "
        f"first state, by {np.sqrt(first):.3g} times their predicted spread (rms), against {np.sqrt(rest):.3g} "
        f"over the rest of the record, most at t = {record['peak_s']:.3g} s (diagnostics.start_check). The "
        "default prior of a nonlinear system's first state is near rest (docs/config.md, [initial]); for a "
        "record cut from motion the estimates near its start, and possibly beyond, are then wrong or "
        "unconverged. Give an [initial] section (the displacements' and velocities' mean and sd, or cov, at "
        "the first sample), or start the record before the motion. If the structure was at rest there, a "
        "force far beyond the [force] prior in that period (an impact, a step) misfits the same way: widen "
        "the prior's variance."
    )


def gaussian_approximation_warning(problem: Problem, result: RunResult) -> None:
    """``ekf``/``ukf`` on a nonlinear system: its bands are a Gaussian approximation's and may be too
    narrow, which no convergence check can show. Measured (2026-12-04) on acceleration-only records of a
    strongly stiffening Duffing (m 1, c 0.5, k 20, k3 200, Matérn-3/2, the stiffness up to 3x at the
    peaks; 12 s at 50 Hz, from rest and cut 2-9 s into the motion): ``ekf``'s ±3 sd band held the true
    force on 13-73 % of the samples (43 % from rest), ``ukf``'s on 90-100 % (100 % from rest), ``pgas``'s
    on 98 % from rest (not converged in 150 s, flagged). An earlier sweep: a softening Duffing under
    ``ekf`` ±1 / ±3 sd 30 / 97 %, strongly stiffening ones 52 / 93 % and 53 / 96 %."""
    method = problem.inference.method
    if method not in ("ekf", "ukf") or problem.model.system.is_linear:
        return
    measured = (
        "ekf's ±3 sd band held the true force on 13-73 % of the samples, where ukf's held it on 90-100 % of "
        'the same records; prefer method = "ukf"'
        if method == "ekf"
        else "ukf's ±3 sd band held the true force on 90-100 % of the samples (ekf's on as few as 13 %)"
    )
    result.diagnostics.setdefault("warnings", []).append(
        f"method {method!r} is a Gaussian approximation of a nonlinear model: its bands can be too narrow "
        "where the nonlinearity is strong against what the sensors pin down (measured on acceleration-only "
        f"records of a strongly stiffening Duffing: {measured}; docs/nonlinear.md). "
        'method = "pgas" samples the exact posterior: run it to check.'
    )
