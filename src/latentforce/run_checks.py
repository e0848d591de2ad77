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


#: the log Bayes factor of a wide first state over the default near-rest one above which a nonlinear
#: record is taken to start in motion (e^10: about 22 000 to 1)
START_LOG_BAYES = 10.0
#: the wide first state's variance of displacements and velocities against the default's: the
#: linearised structure's stationary spread (the default is a tenth of it in sd)
WIDE_START = 100.0


def start_in_motion(problem: Problem, params: dict, y, mask, time) -> tuple[dict | None, str | None]:
    """``(record, warning)``: does a nonlinear record seem to start in motion, against the default prior
    of its first state (near rest, :meth:`latentforce.models.LatentForceModel.default_initial`)?

    The extended Kalman filter's log-likelihood of the record at ``params`` from that prior and from a
    wide one (the displacements' and velocities' variances :data:`WIDE_START` times larger: the
    linearised structure's stationary spread): their difference is the log Bayes factor of "the record
    starts somewhere in the structure's usual motion" against "near rest". A record from rest gives a
    negative one (the wide prior spreads its mass where the data are not); a record cut from motion a
    large positive one. Measured (2026-12-04, ``ekf``): from rest -78 to -1 (a stiffening Duffing,
    the paper's Duffing with and without displacement, the bouc-wen, duffing-params and frame demos);
    a Duffing cut 2, 4, 6 and 9 s into its motion +579, +615, +14 (the cut where it moved least, 0.45
    of its stationary sd) and +358; a Duffing at rest hit 0.1 s in by a blow ten times the force
    prior's sd -17. The window test this replaces (the first period's normalised innovations against
    the rest's) missed the 9 s cut (its misfit went into the force) and warned on the blow.
    ``(None, None)`` where it does not apply: a linear system (its default start is stationary), an
    ``[initial]`` given, a method other than ``pgas``/``ekf``/``ukf``."""
    model, method = problem.model, problem.inference.method
    if model.system.is_linear or problem.initial is not None or method not in ("pgas", "ekf", "ukf"):
        return None, None
    from latentforce.compile import call
    from latentforce.estimate_particles import _mechanical_initial
    from latentforce.inference.gaussian import for_parameters

    time = np.asarray(time, dtype=float)
    dt = float(time[1] - time[0])
    m0, P0 = _mechanical_initial(problem, params)
    widen = np.ones(len(m0))
    widen[: 2 * model.ndof] = np.sqrt(WIDE_START)  # displacements and velocities (not hysteretic states)
    y0, mask = np.where(mask, y, 0.0), np.asarray(mask, dtype=bool)
    lls = []
    for P in (P0, P0 * np.outer(widen, widen)):  # one compiled program: the start is its argument
        loglik, _ = for_parameters("ekf", model, dt, problem.inference.discretisation, (m0, P))
        lls.append(float(call(loglik, numbers(params), y0, mask)))
    log_bf = lls[1] - lls[0]
    record = {"log_bayes_factor": log_bf, "log_likelihood_rest": lls[0], "log_likelihood_wide": lls[1]}
    if not np.isfinite(log_bf) or log_bf <= START_LOG_BAYES:
        return record, None
    return record, (
        f"the record seems to start in motion: the extended Kalman filter finds the data e^{log_bf:.0f} times "
        "more probable from a first state spread over the structure's usual motion (the linearised "
        "system's stationary spread) than from the default near-rest one (diagnostics.start_check: the log "
        "Bayes factor). The default prior of a nonlinear system's first state is near rest (docs/config.md, "
        "[initial]); for a record cut from motion the estimates near its start, and possibly beyond, are "
        "then wrong, with bands too narrow to show it. Give an [initial] section (the displacements' and "
        "velocities' mean and sd, or cov, at the first sample), or start the record before the motion."
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
