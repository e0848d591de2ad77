"""Steps of the nonlinear methods' model per data sample (``[system].steps_per_sample``).

``pgas``, ``ekf`` and ``ukf`` advance their discrete model (:mod:`latentforce.inference.particle_model`)
one step per sample: the force's states and the mechanical states' within-step noise are the latent
at each sample. For a linear system that model is the exact discretisation at any step. For a
hysteretic one it is not: the within-step noise is that of the structure linearised about rest, and
the hysteretic force's own part of it (:func:`~latentforce.inference.particle_model.internal_noise`)
is a bound on how far the loop's tangent leaves the rest value. On a coarse step that approximation
shows. Measured (2026-12-04) on a Bouc-Wen oscillator (the benchmark's beta, gamma, nu = 1, alpha
3e4, Matérn-1/2 force of lengthscale 0.05 s, accelerometer and strain gauge) at 200 Hz, about 6
samples per period of its linearised mode, ``ukf`` at the truth's parameters, the same data with
``k`` model steps per sample (the samples between missing):

=====  ==============================  ===========================  ===========
k      force: +-1/+-2 sd, NMSE, sd     hysteretic force: the same   ``ukf`` s
=====  ==============================  ===========================  ===========
1      91/99 %, 0.19 %, 3.2 N          93/99 %, 0.56 %, 3.1 N       4
2      81/99 %, 0.05 %, 1.3 N          88/99 %, 0.08 %, 1.0 N
4      69/98 %, 0.04 %, 0.96 N         73/98 %, 0.05 %, 0.53 N
8      68/97 %, 0.04 %, 0.93 N         69/96 %, 0.05 %, 0.47 N
=====  ==============================  ===========================  ===========

and ``pgas`` the same (1: 90 / 92 % inside +-1 sd, 3: 70 / 77 %, 6: 68 / 72 %; the smoother move
accepting 0.3 % of its proposals at 1 and 22 % at 3). One step per sample gives bands 3.4 times
too wide on the force and a mean 5 times further from the truth; the grid converges by 4. The
velocity and displacement, pinned by the sensors, agree at every k. Without the strain gauge (the
posterior wide anyway), and on ``demo frame``'s record (100 Hz, its brace's alpha 1e4 on 5 kg floors,
accelerometers only), 1, 3 and 6 steps gave the same posterior to the digits shown.

So where the config does not fix it (``"auto"``, the default), ``ekf`` and ``ukf`` refine by themselves
and ``pgas`` warns: :func:`choose` tests the grid on the
record itself: on a system with hysteretic states whose fastest mode linearised about rest has
``omega dt`` above :data:`FINE_OMEGA_DT` it runs the unscented smoother (seconds, at the
parameters' fixed or init values) with 1, 2, 4 ... steps per sample and takes the first ``k`` whose
posterior of the force at the samples agrees with ``2k``'s: the median over the samples of
``|mean_k - mean_2k| / sd_2k`` at most :data:`MEAN_TOLERANCE` and the median ratio of the sds within
:data:`SD_TOLERANCE` of 1. On the record above: 0.58 and 2.5 for 1 against 2, 0.15 and 1.29 for 2
against 4, 0.036 and 1.03 for 4 against 8, so 4. The tolerances sit between that record and the
calibration suite's Bouc-Wen records, which keep one step: the benchmark at 750 Hz with a
Matérn-1/2 force of lengthscale 0.01 s differs most (0.16 and 1.16 for 1 against 2; its ``pgas``
force bands at one step hold the truth on 80 % of the samples at +-1 sd, within the 55-85 % rule),
the other orders 0.009-0.02, the nu = 2 loop at 500 Hz at most 0.01, the frame 0.022. Only the
force is compared: on the nu = 2 loop the hysteretic force's sds at 1, 2, 4 and 8 steps kept
changing by factors of 2-40 from one grid to the next while the force's agreed to 1 % and its
bands were calibrated at one step (69 / 95 / 99.8 %; the hysteretic force's over-covered, 93-96 %
inside +-1 sd: wide, not wrong). Other nonlinear systems keep one step: their within-step noise is
the linear part's, exact at any step. Measured on a stiffening Duffing oscillator at 50 Hz (omega dt
0.63 about rest, the cubic spring's rms force 1.5 times the linear one's, accelerometer and a sharp
displacement sensor): 1 against 2, 4 and 8 steps 0.06 sd apart, sds within 2 %
(``tests/test_latent_grid.py``). A run then costs ``k`` times as much per iteration;
``steps_per_sample = 1`` in ``[system]`` keeps the faster, wider answer.

``pgas`` keeps one step under "auto" where the check asks for more, and its warning names the count
(:func:`warning`; ``diagnostics.grid_check.recommended``): its per-iteration cost grows with ``k`` and
on the record above, alpha inferred, the refined grid converged more slowly (3 steps: R-hat 1.047 at
600 s where one step converged in 585 s; 4 steps at the config's 150 s cap: R-hat 1.74 in 426 s of
wall time beside a test run, the warm-up not counted against the cap, against 1.038 at one step).
One step's bands are wide, not wrong (force +-3 sd 100 %); ``steps_per_sample = k`` gives the sharper
answer where the time is there. A check that fails (the unscented smoother breaking down on some
grid) keeps one step and says why in ``summary.json``.

The results are reported at the samples only (:func:`on_samples`); ``summary.json`` records the
count and the check (``diagnostics.steps_per_sample``, ``diagnostics.grid_check``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from latentforce.io.data import Dataset

#: "auto" takes one step without the check where the structure's fastest mode, linearised about rest,
#: has omega dt at most this: the check's record had converged at 0.25 (4 steps against 8: 0.036 sd),
#: the benchmark's passes at 0.30 (1 against 2: 0.16 sd); the check costs 10-30 s, mostly compiling
FINE_OMEGA_DT = 0.3
#: the most model steps per sample "auto" takes (and the config's limit, io/schema.py)
MAX_STEPS = 8
#: two grids agree where the median over the samples of |mean_k - mean_2k| / sd_2k of the force is at
#: most this (module doc: between 0.16, the calibrated benchmark record's, and 0.58)
MEAN_TOLERANCE = 0.25
#: ... and the median ratio sd_k / sd_2k is within this of 1 (1.16 calibrated, 2.5 not)
SD_TOLERANCE = 0.25


def refine(dataset: Dataset, k: int) -> Dataset:
    """``dataset`` on a grid ``k`` times finer: the samples at every ``k``-th step, nothing observed
    (NaN, mask False) and no truth in between."""
    if k == 1:
        return dataset
    T = len(dataset.time)
    Tf = (T - 1) * k + 1
    time = dataset.time[0] + np.arange(Tf) * (dataset.dt / k)
    time[::k] = dataset.time

    def spread(a):
        a = np.asarray(a)
        out = np.full((Tf, *a.shape[1:]), np.nan if a.dtype.kind == "f" else False, dtype=a.dtype)
        out[::k] = a
        return out

    return dataset._replace(
        time=time,
        dt=dataset.dt / k,
        values=spread(dataset.values),
        mask=spread(dataset.mask),
        truth={n: spread(np.asarray(v, dtype=float)) for n, v in dataset.truth.items()},
    )


def on_samples(result, k: int, common: dict):
    """A result of the ``k``-times finer grid (:func:`refine`) at the record's samples: every state's
    and output's mean, sd and stored paths there, with the record's own time, data and truth."""
    if k == 1:
        return result
    return dataclasses.replace(
        result,
        state_mean={n: np.asarray(v)[::k] for n, v in result.state_mean.items()},
        state_sd={n: np.asarray(v)[::k] for n, v in result.state_sd.items()},
        path_draws={n: np.asarray(v)[:, :, ::k] for n, v in result.path_draws.items()},
        time=common["time"],
        observed=common["observed"],
        truth=common["truth"],
    )


def for_problem(problem, params0: dict, dataset: Dataset) -> tuple[object, Dataset, int, dict | None]:
    """``(problem, run dataset, k, record)``: the model steps per sample for this record (:func:`choose`),
    the dataset on that grid, and the problem with a fixed ``substeps`` count (per sample) spread over
    the ``k`` steps; ``record`` what ``summary.json`` says about the choice (None: one step, nothing
    to say)."""
    k, record = choose(problem, params0, dataset)
    return _substeps_per_step(problem, k), refine(dataset, k), k, record


def _substeps_per_step(problem, k: int):
    """``problem`` with a fixed ``substeps`` count (per sample) spread over ``k`` model steps."""
    if k == 1 or problem.substeps is None:
        return problem
    return problem._replace(substeps=max(1, math.ceil(problem.substeps / k)))


def choose(problem, params0: dict, dataset: Dataset) -> tuple[int, dict | None]:
    """The model steps per sample: the config's ``[system].steps_per_sample``, or ("auto") the grid
    check of the module doc on a system with hysteretic states, one step otherwise."""
    model = problem.model
    if model.system.is_linear or problem.inference.method not in ("pgas", "ekf", "ukf"):
        return 1, None
    if problem.steps_per_sample is not None:
        k = int(problem.steps_per_sample)
        return k, ({"steps_per_sample": k, "chosen": "config"} if k > 1 else None)
    if not model.layout.n_internal:
        return 1, None
    from latentforce.run_checks import natural_frequencies

    try:
        omega_dt = 2.0 * math.pi * float(np.max(natural_frequencies(problem, params0), initial=0.0)) * dataset.dt
    except (TypeError, ValueError, np.linalg.LinAlgError):  # then the check decides
        omega_dt = math.inf
    if omega_dt <= FINE_OMEGA_DT:
        return 1, None
    checks = []
    try:
        coarse = _posterior(problem, params0, dataset, 1)
        k = 1
        while k < MAX_STEPS:
            fine = _posterior(problem, params0, dataset, 2 * k)
            mean_gap, sd_ratio = _disagreement(coarse, fine)
            checks.append({"steps": [k, 2 * k], "mean_gap": mean_gap, "sd_ratio": sd_ratio})
            if mean_gap <= MEAN_TOLERANCE and abs(sd_ratio - 1.0) <= SD_TOLERANCE:
                break
            k, coarse = 2 * k, fine
    except Exception as err:  # noqa: BLE001 - a check that breaks down says nothing of the grid; the run goes on
        failed = f"{type(err).__name__}: {err}"
        return 1, {"steps_per_sample": 1, "chosen": "auto", "check_failed": failed, "checks": checks}
    if k > 1 and problem.inference.method == "pgas":  # module doc: pgas keeps one step and says so
        return 1, {"steps_per_sample": 1, "chosen": "auto", "recommended": k, "checks": checks}
    return k, {"steps_per_sample": k, "chosen": "auto", "checks": checks}


def warning(record: dict | None) -> str | None:
    """The run's warning where ``pgas`` kept one step that the check found too coarse (None if not)."""
    if not record or "recommended" not in record:
        return None
    first, k = record["checks"][0], record["recommended"]
    return (
        "the model's grid is coarse for this record: the unscented smoother's force posterior changes with "
        f"the model steps per sample (1 against 2: means {first['mean_gap']:.2g} sd apart, sds in the ratio "
        f"{first['sd_ratio']:.2g}; it settles at {k}), so pgas's force bands at one step per sample are "
        f"wider than the data support (measured on a Bouc-Wen oscillator at 200 Hz: 91 % of the samples "
        f"inside +-1 sd, 69 % at 4 steps). steps_per_sample = {k} in [system] gives the sharper posterior at "
        f"{k} times the cost per iteration (ekf and ukf refine by themselves); docs/config.md, steps_per_sample."
    )


def _posterior(problem, params0: dict, dataset: Dataset, k: int) -> dict:
    """The unscented smoother's ``{"force": (mean, sd)}`` at the samples, with ``k`` model steps per
    sample (substeps chosen for that step, as a run chooses them)."""
    from latentforce import substeps
    from latentforce.compile import call, numbers
    from latentforce.estimate_particles import gaussian_for
    from latentforce.inference.kalman_mcmc import state_moments

    fine = refine(dataset, k)
    # the substeps a run on this grid would take (the run's method is pgas, ekf or ukf here)
    prob, _ = substeps.for_problem(_substeps_per_step(problem, k), params0, fine.dt)
    _, smoother = gaussian_for(prob, params0, fine.dt, kind="ukf")
    mask = np.asarray(fine.mask, dtype=bool)
    sm = call(smoother, numbers(params0), np.where(mask, fine.values, 0.0), mask)
    moments = state_moments(prob.model, sm.means, sm.covs)
    keep = ("force",)
    out = {n: (np.asarray(m)[::k], np.asarray(s)[::k]) for n, (m, s) in moments.items() if n in keep}
    if not all(np.all(np.isfinite(m)) and np.all(np.isfinite(s)) for m, s in out.values()):
        raise FloatingPointError(f"the unscented smoother's posterior at {k} steps per sample is not finite")
    return out


def _disagreement(coarse: dict, fine: dict) -> tuple[float, float]:
    """``(mean gap, sd ratio)``: the worst over the quantities' columns of the median over the
    samples of ``|mean_c - mean_f| / sd_f``, and of the median ``sd_c / sd_f`` the one furthest from 1."""
    gaps, ratios = [], []
    for name, (mc, sc) in coarse.items():
        mf, sf = fine[name]
        sf = np.maximum(sf, np.finfo(float).tiny)
        gaps.append(np.median(np.abs(mc - mf) / sf, axis=0))
        ratios.append(np.median(sc / sf, axis=0))
    gaps, ratios = np.concatenate([np.ravel(g) for g in gaps]), np.concatenate([np.ravel(r) for r in ratios])
    return float(np.max(gaps)), float(ratios[np.argmax(np.abs(ratios - 1.0))])
