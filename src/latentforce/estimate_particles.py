"""The particle methods' part of :func:`latentforce.estimate.run`: ``pgas`` packed into a
``RunResult``, and the mechanical start shared with ``ekf``/``ukf`` (split from ``estimate.py``)."""

from __future__ import annotations

import functools
import re
import time as _time

import numpy as np

from latentforce.compile import jit, numbers
from latentforce.errors import LatentForceError
from latentforce.io.config import Problem, config_key
from latentforce.io.data import Dataset
from latentforce.outputs import path_outputs, sample_moments
from latentforce.outputs import split as split_outputs
from latentforce.results import RunResult, summarise_parameters

#: the most iterations an "auto" pgas run makes (it stops earlier when converged or at max_time)
PGAS_AUTO_ITERATIONS = 50_000


#: below this mean ancestor switch rate an unconverged pgas run's warning says why (docs/nonlinear.md:
#: 0.08 / 0.008 / 0.0002 at Matérn-3/2 / 5/2 / 7/2 on an acceleration-only Duffing record that did
#: not converge; 0.6 on the paper's Matérn-1/2 case that does) ...
LOW_SWITCH_RATE = 0.1
#: ... unless the smoother move renewed the path instead (acceptance 0.5-1 with a displacement
#: channel, where 5/2 and 7/2 converge at switch rates of 0.01 and 5e-5; 0 with acceleration alone)
LOW_SMOOTHER_ACCEPTANCE = 0.05


def low_switch_advice(
    switch_rate: float,
    smoother_acceptance: float = float("nan"),
    displacement_measured: bool = False,
    smooth_force: bool = True,
) -> str:
    """What an unconverged pgas run's warning adds when neither its sweep nor its smoother move
    renewed the path ("" if not). ``displacement_measured``: a displacement or strain channel is
    among the sensors, where the smoother move's linearised proposal usually renews the path, so its
    failure points at the model's scale, not at a missing sensor. ``smooth_force``: the force model
    has a Matérn-3/2 or smoother term (:func:`kernel_is_smooth`); with Matérn-1/2 alone the sweep still
    renews the path at these rates, slowly, and the advice says so instead of blaming smoothness."""
    if not switch_rate < LOW_SWITCH_RATE or smoother_acceptance >= LOW_SMOOTHER_ACCEPTANCE:
        return ""
    head = (
        f" The particle sweep hardly renewed the path (ancestor switch rate {switch_rate:.3f}), nor did "
        f"the smoother move (acceptance {smoother_acceptance:.3f}); "
    )
    head += (
        "running longer helps little then. "
        if smooth_force
        else "with a Matérn-1/2 force the sweep still renews the path, slowly, so a larger max_time helps "
        "(on our unconverged Matérn-1/2 cases the bulk ESS grew about in proportion to the run's time). "
    )
    if displacement_measured:
        return head + (
            "With a displacement (or strain) channel that move usually accepts most of its proposals; here "
            "its linearisation about the path is poor: a nonlinearity strong on the scale of the record's "
            "motion, a record sampled coarsely for the structure's motion (measured on a Bouc-Wen "
            "oscillator over the same 0.8 s: 5 % accepted at about 6 samples per period of its linearised "
            "mode, 30 % at 21; fewer on longer records), or a "
            "mechanical step too coarse for the structure's rate (a [system].substeps fixed below the need "
            "is warned about; diagnostics.substeps gives the count used). Compare with "
            'method = "ukf"' + (" and with a Matérn-1/2 force model." if smooth_force else ".")
        )
    if not smooth_force:
        return head + (
            "Adding a displacement (or strain) sensor, where one can be had, lets the smoother move renew "
            'the path; compare with method = "ukf".'
        )
    return head + (
        "This is the known weakness of a smooth force (Matérn-3/2 or smoother) on a nonlinear system "
        "seen without a displacement channel (docs/nonlinear.md): add a displacement sensor if one can "
        "be had (with one, pgas converged and was calibrated at every Matérn order on our Duffing "
        "cases, benchmarks/results/nonlinear_calibration_orders.md), or compare with a Matérn-1/2 "
        'force model and with method = "ukf".'
    )


def kernel_is_smooth(kernel) -> bool:
    """Whether a force kernel has a Matérn-3/2 or smoother term (a state dimension above one: the
    driving noise enters only its highest derivative), through sums."""
    if hasattr(kernel, "terms"):
        return any(kernel_is_smooth(t) for t in kernel.terms)
    if hasattr(kernel, "k1"):
        return kernel_is_smooth(kernel.k1) or kernel_is_smooth(kernel.k2)
    return int(kernel.dim) > 1


def softening_hint(values: dict) -> str:
    """``"; here ..."``, naming the cubic stiffnesses (a Duffing's ``k3``, a cubic element's) that are
    negative in ``values`` (parameter name -> a number, or an array of draws: any negative draw counts),
    for a message on a model that overflowed; "" if none. A negative k3 is a softening spring: its
    restoring force turns over beyond some displacement (for a Duffing, |z| = sqrt(k / |k3|)), and a
    structure pushed past it escapes to infinity, so a model that cannot follow the data overflows."""
    negative = []
    for name, value in values.items():
        if name == "k3" or name.endswith("_k3"):
            v = np.asarray(value, dtype=float)
            if v.size and np.nanmin(v) < 0:
                negative.append(f"{config_key(name)} = {np.nanmin(v):.4g}")
    if not negative:
        return ""
    return (
        f"; here a cubic stiffness is negative ({', '.join(negative)}): a softening spring, whose restoring "
        "force turns over beyond some displacement, past which the structure escapes. Check its sign and "
        "its unit (N/m^3)"
    )


#: a monitored quantity's time index in its name (``force[t=12]``), before :func:`_label_times`
_TIME_INDEX = re.compile(r"\[t=(\d+)\]")

#: the share of the record, from its first sample, where an unconverged pgas run's worst quantities
#: point at the initial hysteretic force (:func:`hysteretic_start_advice`)
START_SHARE = 0.05


def unmeasured_displacement_advice(record: dict, displacement_measured: bool) -> str:
    """What an unconverged pgas run's warning adds when its slowest quantity is a displacement and no
    displacement or strain channel is measured ("" if not; a diverged chain's advice is the model's).

    With velocity or acceleration alone the displacement's slow content is seen only through the
    structure's nonlinearity and the force's prior, and the chains wander along it although the
    smoother move accepts its proposals (so :func:`low_switch_advice` says nothing): a stiffening
    Duffing with velocity alone (``benchmarks/results/nonlinear_calibration_vel.md``) converged in 41 s
    at Matérn-3/2 but ended at R-hat 1.21, bulk ESS 15 at Matérn-5/2 after 180 s (smoother move 17-29 %
    accepted), its worst quantities displacements, while with a displacement channel our Duffing
    records converged at every order in 28-40 s (docs/nonlinear.md)."""
    if displacement_measured or record.get("converged", False) or record.get("diverged_chains"):
        return ""
    worst = record.get("worst", [])
    if not worst or not str(worst[0]["name"]).startswith("displacement"):
        return ""
    return (
        " The slowest quantity is the displacement, which no sensor measures: its slow content is seen "
        "only through the structure's nonlinearity and the force's prior, so the chains wander along it "
        "and running longer gains slowly. Add a displacement (or strain) sensor where one can be had (with "
        "one, our 256-sample Duffing records converged at every Matérn order in under a minute), and compare with "
        'method = "ukf".'
    )


def hysteretic_start_advice(record: dict, has_hysteresis: bool, initial_given: bool, T: int) -> str:
    """What an unconverged pgas run's warning adds when its slowest quantities sit at the record's start
    on a system with hysteretic states and no ``[initial]`` was given ("" if not). ``record``: the
    verdict with time *indices* in its names (``force[t=12]``), before :func:`_label_times`.

    There the slow coordinate is the initial hysteretic force r0 traded against the force: the
    acceleration fixes their difference, so the data leave r0 as wide as its prior (docs/nonlinear.md,
    "Bouc-Wen hysteresis"). A start known to be at rest in a virgin state removes it: on the Bouc-Wen
    benchmark's Matérn-5/2 record (450 samples, acc + disp, 180 s cap) the default start ended at R-hat
    1.83, bulk ESS 6, while [initial] with r0's sd 1.3 N (1 % of its peak) converged in 76-113 s over
    three records, and at Matérn-7/2 in 70 s (docs/nonlinear.md, "A start known to be virgin";
    ``benchmarks/results/nonlinear_calibration_bouc_wen_virgin.md``). Since the profile move
    (:mod:`latentforce.inference.profile_move`) the default start converges there too (104-107 s), so
    this text is for records still slow at their start, where a known start is the faster answer."""
    if not has_hysteresis or initial_given or record.get("converged", False):
        return ""
    first = max(1, int(np.ceil(START_SHARE * T)))
    if not any(
        (m := _TIME_INDEX.search(w["name"])) is not None and int(m.group(1)) <= first
        for w in record.get("worst", [])[:3]
    ):
        return ""
    return (
        " The slowest quantities include the record's first samples, where the initial hysteretic force "
        "trades against the force (the acceleration fixes their difference, so the data hardly narrow its "
        "prior). If the structure was at rest in a virgin state when the record began, say so: [initial] "
        "with a small sd on the hysteretic force (about 1 % of its expected peak; docs/config.md, "
        '"[initial]"). On our Bouc-Wen benchmark at Matérn-5/2 it converged in 74-113 s over three records '
        "(from the default start: 104-107 s)."
    )


def _label_times(record: dict, time: np.ndarray) -> dict:
    """A convergence record with ``name[t=index]`` relabelled ``name[t=time]``."""

    def relabel(name):
        return _TIME_INDEX.sub(lambda m: f"[t={time[int(m.group(1))]:.6g}]", name)

    out = dict(record)
    out["worst"] = [dict(w, name=relabel(w["name"])) for w in record.get("worst", [])]
    return out


@functools.partial(jit, static_argnames=("model",))
def _default_initial(params, *, model):
    # one compiled program: op by op its small solves compiled some dozens of programs
    return model.default_initial(params)


def _mechanical_initial(problem: Problem, params0: dict):
    """The mechanical states' ``(mean, cov)`` start of the particle sampler's model (``pgas``,
    ``ekf``, ``ukf``): the user's ``[initial]``; else None for a linear system (the joint
    stationary start at each parameter value), the model's near-rest default for a nonlinear one."""
    model = problem.model
    mech = model.layout.mech
    if problem.initial is not None:
        mean, cov = problem.initial
        return np.asarray(mean)[mech], np.asarray(cov)[mech, mech]
    if model.system.is_linear:
        return None
    # one compiled program: op by op its small solves compiled some dozens of programs
    m0, P0 = _default_initial(numbers(params0), model=model)
    return np.asarray(m0)[mech], np.asarray(P0)[mech, mech]


def gaussian_for(problem: Problem, params0: dict, dt: float, kind: str | None = None, outputs=()):
    """``(loglik, smoother)`` of the problem's ``ekf``/``ukf`` (``kind`` in place of its method) at the
    model step ``dt``, started from :func:`_mechanical_initial` at ``params0``
    (:func:`latentforce.inference.gaussian.for_parameters`)."""
    from latentforce.inference.gaussian import for_parameters

    settings = problem.inference
    initial = _mechanical_initial(problem, params0)
    return for_parameters(kind or settings.method, problem.model, dt, settings.discretisation, initial, outputs)


def _run_pgas(
    key,
    problem: Problem,
    dataset: Dataset,
    params0: dict,
    y,
    mask,
    common: dict,
    progress,
    t0: float,
    channels=None,
    checkpoint=None,
) -> RunResult:
    """Particle Gibbs (``pgas``) for any system; packs the sampler output into a RunResult."""
    from latentforce.inference import convergence
    from latentforce.inference.pgas import run_pgas
    from latentforce.inference.pgas_defaults import DISPLACEMENT_CHANNELS

    model = problem.model
    settings = problem.inference
    free = {n: (spec.prior, spec.init) for n, spec in problem.free.items()}
    # The initial state: the user's [initial] for the mechanical states (the force states
    # start from their stationary GP distribution); else for a linear system the joint
    # stationary distribution at the current hyperparameters (particle_model.ParticleModel), for a
    # nonlinear one the model's near-rest default at the initial hyperparameters.
    initial = _mechanical_initial(problem, params0)
    # An inferred noise level gets an exact Gibbs step whose conditional is proper only with
    # more than two observed samples of its channel (inference/noise_gibbs.py).
    observed_n = np.sum(mask & np.isfinite(y), axis=0)
    for i, s in enumerate(model.sensors):
        if s.noise_param in problem.free and observed_n[i] <= 2:
            raise LatentForceError(
                f"{problem.config_path}: [[sensors]][{i}].noise_std (column {s.name!r}) is inferred, but the "
                f'column has {int(observed_n[i])} observed samples; method "pgas" needs more than two to '
                "infer a noise level. Give noise_std as a number."
            )
    # PGAS needs a conditional resampling scheme; multinomial is the valid one we have.
    out = run_pgas(
        key,
        model,
        params0,
        free,
        np.where(mask, y, np.nan),
        mask,
        dataset.dt,
        particles=settings.particles,
        iterations=settings.iterations,
        burn_in=settings.burn_in,
        state_every=settings.state_every,
        chains=settings.chains,
        mh_steps=settings.mh_steps,
        discretisation=settings.discretisation,
        proposal=settings.proposal,
        resampling="multinomial",
        thin_draws=settings.thin_draws,
        initial=initial,
        progress=progress,
        channels=channels,
        target_ess=settings.target_ess,
        max_time=settings.max_time,
        max_iterations=PGAS_AUTO_ITERATIONS,
        checkpoint=checkpoint,
    )
    paths = model.layout.quantities(out.trajectories)
    state_mean = {n: np.asarray(v) for n, v in out.state_mean.items()}
    state_sd = {n: np.asarray(v) for n, v in out.state_sd.items()}
    # Each stored trajectory came from the sweep of one Gibbs block; pair it with the
    # hyperparameters drawn at the end of that block (conditional on that trajectory).
    k = settings.state_every
    burn_in = int(out.diagnostics.pop("burn_in_run"))  # settings.burn_in unless max_time cut the warm-up
    burn_blocks = -(-burn_in // k)
    iterations = int(out.diagnostics.pop("iterations_run"))
    thin = int(out.diagnostics.pop("thin"))
    slots = np.arange(out.trajectories.shape[1])
    idx = np.clip((burn_blocks + slots * thin) * k + k - 1 - burn_in, 0, max(iterations - 1, 0))
    param_draws = {n: v[:, idx] for n, v in out.theta.items()}
    if problem.outputs:  # from the stored paths, the acceleration from the equation of motion
        # a sampled system parameter (m, c, k, k3 ...): each path's at its own draw
        sampled = path_outputs(
            model,
            problem.outputs,
            params0,
            paths["displacement"],
            paths["velocity"],
            paths["force"],
            draw_params={n: param_draws[n] for n in out.names if n in model.system.param_names},
            r=paths.get("hysteretic_force"),
        )
        out_mean, out_sd, out_paths = split_outputs(problem.outputs, *sample_moments(sampled), sampled)
        state_mean.update(out_mean)
        state_sd.update(out_sd)
        paths.update(out_paths)
    pooled = {n: v.reshape(-1) for n, v in out.theta.items()}
    point = {f"{n}_mean": float(np.mean(v)) for n, v in pooled.items()}
    point.update({f"{n}_median": float(np.median(v)) for n, v in pooled.items()})
    ll = out.log_likelihood
    diagnostics = dict(out.diagnostics)
    record = diagnostics.pop("convergence")
    diagnostics.update(
        {
            "iterations": iterations,
            "iterations_setting": "auto" if settings.iterations is None else settings.iterations,
            "burn_in": settings.burn_in,
            "warmup": burn_in,
            "state_every": k,
            "chains": settings.chains,
            "discretisation": settings.discretisation,
            "proposal": settings.proposal,
            "resampling": "multinomial",
            "log_likelihood_note": "particle-filter estimate of log p(y | theta), mean over the last sweeps",
        }
    )
    from latentforce.models import is_hyper_name
    from latentforce.priors import Flat

    flat = [n for n, (prior, _) in free.items() if isinstance(prior, Flat) and is_hyper_name(n)]
    if flat:
        record_s = len(dataset.time) * dataset.dt
        diagnostics.setdefault("warnings", []).append(
            f"flat prior on {', '.join(flat)}: on a record of {record_s:.3g} s a Matérn force's variance "
            "and lengthscale are pinned mainly in one combination (variance/lengthscale^(2p+1) for "
            "Matérn-(p+1/2)), so with a flat "
            "prior the posterior can be improper along that ridge and the slow part of the force "
            "wanders. Use proper priors (e.g. lognormal) on the force hyperparameters; see docs/config.md."
        )
    # The run's verdict: the hyperparameters (every iteration) and the displacement, velocity
    # and force at 24 spread times (every sweep); its time indices become the record's times.
    start_advice = hysteretic_start_advice(
        record, bool(model.layout.n_internal), problem.initial is not None, len(dataset.time)
    )
    record = _label_times(record, np.asarray(dataset.time))
    message = convergence.warning_message(record, "pgas", softening_hint({**problem.fixed, **out.theta}))
    if message:
        advice = ""
        if not record.get("diverged_chains"):  # a diverged chain's advice is the model's (in message)
            switch = float(np.mean(out.switch_rate)) if np.size(out.switch_rate) else float("nan")
            smoother = out.diagnostics.get("acceptance_smoother")
            smoother = float(np.mean(smoother)) if smoother else float("nan")
            measured = any(s.quantity in DISPLACEMENT_CHANNELS for s in model.sensors)
            advice = (
                low_switch_advice(switch, smoother, measured, kernel_is_smooth(model.kernel))
                or unmeasured_displacement_advice(record, measured)
            ) + start_advice
        diagnostics.setdefault("warnings", []).append(message + advice)
    cut = convergence.warm_up_cut_warning(settings.burn_in, burn_in, settings.max_time)
    if cut:
        diagnostics.setdefault("warnings", []).append(cut)
    truth = common["truth"]
    if truth:
        from latentforce.results import by_column, coverage

        diagnostics["coverage_3sd"] = by_column(coverage, truth, out.state_mean, out.state_sd)
    return RunResult(
        method="pgas",
        state_mean=state_mean,
        state_sd=state_sd,
        param_draws=param_draws,
        param_chains={n: np.asarray(v) for n, v in out.theta.items()},
        path_draws=paths,
        sample_stats={
            "log_likelihood": ll,
            "switch_rate": out.switch_rate,
            "ess_per_particle": out.ess,
            # the parameters' Metropolis acceptance, per chain (INTERFACE: sample_stats holds the acceptance);
            # none where no parameter is sampled
            **({"acceptance": np.asarray(out.acceptance, dtype=float)} if np.size(out.acceptance) else {}),
        },
        acceptance=[float(a) for a in out.acceptance],
        log_likelihood=float(np.mean(ll[:, -max(1, ll.shape[1] // 10) :])) if ll.size else float("nan"),
        point_estimate=point,
        diagnostics=diagnostics,  # made JSON-safe by the writer
        param_summary=summarise_parameters(out.theta) if out.theta else None,
        convergence=record,
        wall_time_s=_time.perf_counter() - t0,
        **common,
    )
