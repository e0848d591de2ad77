r"""Calibration of the samplers: simulation-based calibration, and coverage over repeated records.

Two checks that a sampler's posterior means what it says.

**Simulation-based calibration** (SBC; Talts, Betancourt, Simpson, Vehtari &
Gelman 2018, arXiv:1804.06788, Algorithm 2). For :math:`n = 1 \dots N`: draw
:math:`\tilde\theta \sim \pi(\theta)` from the prior, simulate a record
:math:`\tilde y \sim p(y \mid \tilde\theta)` exactly, run the sampler on it,
thin its draws to :math:`L` roughly independent ones (stride from the run's
ESS, as the paper advises) and take the rank
:math:`r = \#\{l : \theta_l < \tilde\theta\}` of the truth among them. If the
sampler draws from the exact posterior, :math:`r` is uniform on
:math:`\{0, \dots, L\}` for every parameter (Theorem 1 of the paper),
whatever the record length. Uniformity is tested per parameter on
:math:`u = (r + V)/(L + 1)`, :math:`V \sim U(0, 1)`, which is uniform on
:math:`(0, 1)` for any :math:`L` (so a run thinned to fewer than :math:`L`
draws still counts): a :math:`\chi^2` test on :math:`B` equal bins and a
Kolmogorov-Smirnov test. Under SBC the central-interval coverage is exactly
nominal too, so those rows report it as well.

**Coverage** at fixed true parameters :math:`\theta^*`: :math:`R` records
simulated at :math:`\theta^*`, each run; the fraction of runs whose central
50 % and 90 % posterior intervals contain :math:`\theta^*`. With weak priors
and long records (Bernstein-von Mises) it should be 0.5 and 0.9, within the
binomial standard deviation :math:`\sqrt{p(1-p)/R}`; reported beside it are
the fraction of runs the sampler's own verdict calls converged, the median
over runs of the R-hat and the bulk ESS, and the seconds per run.

Records are exact draws from the discrete linear-Gaussian model
(:func:`latentforce.inference.kalman_mcmc.linear_gaussian`: the same
:math:`A, Q, H, R, m_0, P_0` as the likelihood), so any miscalibration is the
sampler's, not a discretisation error. The samplers run as a user runs them:
``iterations = "auto"`` (until R-hat and ESS say converged, or ``max_time``),
the default burn-in and chains.

**Compiled programs across replicates.** ``run_kalman_mcmc`` and
``run_kalman_nuts`` build their jitted programs inside each call, so every
replicate traces and compiles them anew; the record is an argument of those
programs, not a constant, so their lowered text is the same from one
replicate to the next. JAX's persistent compilation cache (pointed at a
temporary directory for this process, :func:`latentforce.compile.persistent_cache`)
therefore serves every replicate after the first. Measured on the SBC case
(T = 300, 4 chains, 500 + 500 iterations of kalman-mcmc, 2 cores):
4.6 s per replicate without it, 1.3 s with it, the draws identical.

**Adding case families.** A :class:`Case` names its family; a
:class:`Family` says how to simulate a record and how to run each of its
samplers; :data:`FAMILIES` and :func:`cases` list them. The nonlinear
samplers join by adding a family (its simulator and runners) and their cases.

Usage::

    python benchmarks/calibration.py --quick     # < 3 min: writes results/calibration_quick.md
    python benchmarks/calibration.py             # full: results/calibration.md (about an hour on 2 cores)
    python benchmarks/calibration.py --only sbc --sbc-replications 50
"""

from __future__ import annotations

import os

# Run as a script: one BLAS thread unless the caller says otherwise (before NumPy loads
# OpenBLAS). The samplers' L-BFGS start (scipy L-BFGS-B) makes ~300 tiny BLAS calls per
# run, and with OpenBLAS's default threads on a busy 2-core machine each setulb call took
# ~3 ms: 4.7 -> 3.4 s per kalman-mcmc replicate of the SBC case with one thread (measured
# with cProfile, 2026-11). Imported (by the tests), it leaves the environment alone.
if __name__ == "__main__":
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import argparse
import dataclasses
import datetime
import math
import platform
import sys
import time
import traceback
import zlib
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

RESULTS_DIR = Path(__file__).resolve().parent / "results"
#: thinned posterior draws per SBC replicate (ranks 0..L)
SBC_DRAWS = 99
#: central intervals whose coverage is reported
LEVELS = (0.5, 0.9)
#: a coverage (or p-value) is flagged when it is this many binomial sd off nominal
FLAG_SD = 3.0
FLAG_P = 0.01
LABELS = {"k": "k", "c": "c", "force_variance": "σ²", "force_lengthscale": "ℓ"}
LABELS.update({f"force_{n}_{i}": f"{LABELS[f'force_{n}']}{i}" for n in ("variance", "lengthscale") for i in range(4)})
SPARK = "▁▂▃▄▅▆▇█"


# ----- cases, families, samplers ----------------------------------------------------------
class Posterior(NamedTuple):
    """What a calibration needs from a run: draws ``{name: (chains, n)}`` and the run's own verdict."""

    draws: dict
    convergence: dict
    info: dict


@dataclasses.dataclass(frozen=True, eq=False)
class Case:
    """A calibration case: a model and its priors (a config dict), a record length and the truth.

    ``truth`` maps each free parameter to its true value (coverage);
    ``None`` draws the truth from the priors in each replicate (SBC).
    """

    name: str
    family: str
    config: dict
    T: int
    dt: float
    truth: dict | None
    samplers: tuple[str, ...]
    description: str
    #: run in quick mode too (the order variants of a case run only in full mode)
    quick: bool = True

    @property
    def kind(self) -> str:
        return "SBC" if self.truth is None else "coverage"


@dataclasses.dataclass(frozen=True)
class Family:
    """How to simulate a record of a case family and how to run each of its samplers.

    ``simulate(rng, problem, params, T, dt) -> (y, mask)``;
    ``run(key, sampler, problem, y, mask, dt, settings) -> Posterior``.
    """

    simulate: Callable
    run: Callable
    #: names of latent quantities ranked besides the free parameters (their truth comes from the
    #: third item ``simulate`` may return, ``{state: (T,) path}``; a name is ``state@t``)
    latent_names: Callable[[int], list] = lambda T: []


def psd_root(S: np.ndarray) -> np.ndarray:
    """A square root ``B B^T = S`` of a symmetric positive semi-definite matrix (eigen, negatives clipped).

    The discrete process noise ``Q`` of a force-driven structure is singular
    to rounding (rank = the force states' dimension), where Cholesky fails.
    """
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


def _initial(problem):
    from latentforce.inference.kalman_mcmc import Initial

    return None if problem.initial is None else Initial(*problem.initial)


def simulate_discrete(rng: np.random.Generator, A, Q, H, R, m0, P0, T: int, records: int | None = None):
    r"""Exact draws from :math:`x_1 \sim N(m_0, P_0)`, :math:`x_{t+1} = A x_t + q_t`,
    :math:`y_t = H x_t + r_t` (the model of :mod:`latentforce.inference.kalman`).

    Returns ``y`` shaped ``(T, d)``, or ``(records, T, d)`` for that many independent records.
    """
    A, Q, H, R, m0, P0 = (np.asarray(a, dtype=float) for a in (A, Q, H, R, m0, P0))
    batch = 1 if records is None else records
    n = m0.size
    x = m0 + rng.standard_normal((batch, n)) @ psd_root(P0).T
    w = rng.standard_normal((T, batch, n)) @ psd_root(Q).T
    xs = np.empty((T, batch, n))
    for t in range(T):
        xs[t] = x
        x = x @ A.T + w[t]
    y = xs @ H.T + rng.standard_normal((T, batch, H.shape[0])) @ psd_root(R).T
    y = np.moveaxis(y, 0, 1)
    return y[0] if records is None else y


def simulate_linear(rng: np.random.Generator, problem, params: dict, T: int, dt: float):
    """An exact record of a linear problem at ``params`` (the likelihood's own discrete model), all observed."""
    from latentforce.inference.kalman_mcmc import linear_gaussian

    y = simulate_discrete(rng, *linear_gaussian(problem.model, params, dt, _initial(problem)), T)
    return y, np.ones(y.shape, dtype=bool)


def run_linear(key, sampler: str, problem, y, mask, dt: float, settings: dict) -> Posterior:
    """``kalman-mcmc`` or ``kalman-nuts`` on the record, "auto" iterations, the problem's priors and inits."""
    from latentforce.inference.kalman_mcmc import run_kalman_mcmc
    from latentforce.inference.kalman_nuts import run_kalman_nuts

    runner = {"kalman-mcmc": run_kalman_mcmc, "kalman-nuts": run_kalman_nuts}[sampler]
    free = {name: (spec.prior, spec.init) for name, spec in problem.free.items()}
    out = runner(
        key,
        problem.model,
        dict(problem.fixed),
        free,
        y,
        mask,
        dt,
        iterations=None,
        initial=_initial(problem),
        **settings,
    )
    info = {
        "acceptance": float(np.mean(out.acceptance)),
        "start": out.start.get("method"),
        "modes": len(out.start.get("modes", [])),
        "draws_per_chain": int(out.draws[out.names[0]].shape[1]),
    }
    if out.sampler_info:
        info.update(
            steps=out.sampler_info.get("mean_integration_steps"), divergences=out.sampler_info.get("divergences")
        )
    return Posterior(out.draws, out.convergence, info)


def _duffing():
    """The pgas family's module (``calibration_duffing.py`` beside this file), loaded by path so
    that this file also works when imported by the tests."""
    import importlib.util

    name = "calibration_duffing"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parent / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def simulate_duffing(rng, problem, params, T, dt):
    return _duffing().simulate(rng, problem, params, T, dt)


def run_duffing(key, sampler, problem, y, mask, dt, settings) -> Posterior:
    return Posterior(*_duffing().run(key, sampler, problem, y, mask, dt, settings))


FAMILIES: dict[str, Family] = {
    "linear": Family(simulate_linear, run_linear),
    "duffing": Family(simulate_duffing, run_duffing, lambda T: _duffing().latent_names(T)),
}

#: sampler settings (keyword arguments of the runner besides the record), full and quick
SETTINGS = {
    "kalman-mcmc": {
        "full": dict(chains=4, burn_in=500, target_ess=400, max_time=120),
        "quick": dict(chains=4, burn_in=500, target_ess=100, max_time=30),
    },
    "kalman-nuts": {
        "full": dict(chains=4, burn_in=300, target_ess=400, max_time=300),
        "quick": dict(chains=2, burn_in=100, target_ess=100, max_time=30),
    },
    "pgas": {
        "full": dict(chains=4, burn_in=500, target_ess=400, max_time=120),
        "quick": dict(chains=4, burn_in=200, target_ess=100, max_time=20),
    },
}
# ekf / ukf with free parameters: kalman-mcmc's random walk on the filter's likelihood
SETTINGS["ekf"] = SETTINGS["ukf"] = SETTINGS["kalman-mcmc"]
#: the nonlinear sampler and, beside it, the Gaussian baselines (their approximate posterior's
#: ranks show where it is too sure)
NONLINEAR_SAMPLERS = ("pgas", "ekf", "ukf")


def _lognormal(median: float, sigma: float, init: float) -> dict:
    return {"prior": "lognormal", "mu": float(np.log(median)), "sigma": sigma, "init": init}


def sdof_config(c: dict, k: dict, variance: dict, lengthscale: dict) -> dict:
    """The small linear case: SDOF, m = 1, Matérn-3/2 force, one acceleration channel (noise sd 0.05)."""
    return {
        "system": {"type": "linear", "m": 1.0, "c": c, "k": k},
        "force": {"kernel": "matern32", "variance": variance, "lengthscale": lengthscale},
        "sensors": [{"column": "acc", "quantity": "acceleration", "dof": 0, "noise_std": 0.05}],
        "inference": {"method": "kalman-mcmc"},
    }


#: SBC: informative priors, so that every prior draw is a plausible structure (about 2 Hz,
#: 1-3 % damping) and force, and the sampler's init (the prior median) is a sensible start.
SBC_CONFIG = sdof_config(
    c=_lognormal(0.5, 0.3, 0.5),
    k=_lognormal(150.0, 0.2, 150.0),
    variance=_lognormal(1.0, 0.5, 1.0),
    lengthscale=_lognormal(0.5, 0.3, 0.5),
)
#: Coverage: weak priors (as tests/test_linear_samplers.py), inits off the truth.
COVERAGE_CONFIG = sdof_config(
    c=_lognormal(0.5, 1.0, 0.8),
    k=_lognormal(150.0, 0.5, 120.0),
    variance=_lognormal(1.0, 2.0, 2.0),
    lengthscale=_lognormal(1.0, 1.0, 0.3),
)
COVERAGE_TRUTH = {"c": 0.5, "k": 158.0, "force_variance": 1.0, "force_lengthscale": 0.5}
LINEAR_SAMPLERS = ("kalman-mcmc", "kalman-nuts")
DT = 0.02

#: SBC of pgas: a stiffening Duffing (at the rms displacement 3 k3 z^2 is comparable to k), a smooth
#: (Matérn-3/2) force, displacement and acceleration channels; the hyperparameters inferred.
DUFFING_SBC_CONFIG = {
    "system": {"type": "duffing", "m": 1.0, "c": 0.5, "k": 10.0, "k3": 1000.0},
    "force": {
        "kernel": "matern32",
        "variance": _lognormal(1.0, 0.5, 1.0),
        "lengthscale": _lognormal(0.5, 0.3, 0.5),
    },
    "sensors": [
        {"column": "disp", "quantity": "displacement", "dof": 0, "noise_std": 0.01},
        {"column": "acc", "quantity": "acceleration", "dof": 0, "noise_std": 0.05},
    ],
    "inference": {"method": "pgas"},
}


#: a small Bouc-Wen case with two of its parameters inferred (issue 22's parameter SBC)
BOUC_WEN_SBC_CONFIG = {
    "system": {
        "type": "bouc-wen",
        "m": 2.0,
        "c": 10.0,
        "k": 5.0e4,
        "alpha": _lognormal(5.0e4, 0.2, 5.0e4),
        "beta": 800.0,
        "gamma": {"prior": "normal", "mean": -1100.0, "sd": 300.0, "init": -1100.0},
        "nu": 1.0,
    },
    "force": {
        "kernel": "matern12",
        "variance": _lognormal(2500.0, 0.5, 2500.0),
        "lengthscale": _lognormal(0.01, 0.3, 0.01),
    },
    "sensors": [
        {"column": "disp", "quantity": "displacement", "dof": 0, "noise_std": 2e-5},
        {"column": "acc", "quantity": "acceleration", "dof": 0, "noise_std": 0.3},
    ],
    # from rest in a virgin state: a small sd on the hysteretic force (docs/config.md, [initial])
    "initial": {"mean": [0.0, 0.0, 0.0, 0.0], "sd": [1e-5, 1e-3, 0.3, 50.0]},
    "inference": {"method": "pgas"},
}


def cases() -> list[Case]:
    """Every calibration case, in the order of the table."""
    duffing = Case(
        "duffing-sbc",
        "duffing",
        DUFFING_SBC_CONFIG,
        65,
        0.05,
        None,
        ("pgas",),
        "Duffing m = 1, c = 0.5, k = 10, k3 = 1000, Matérn-3/2 force, displacement (noise sd 0.01) and "
        "acceleration (0.05), dt = 0.05 s; records drawn from pgas's own discrete model (RK4 step and "
        "within-step noise, `calibration_duffing.py`); priors log-normal: σ² median 1 (0.5), ℓ 0.5 (0.3); "
        "ranks also of the force at 1/8, 3/8, 5/8, 7/8 of the record",
    )
    return [
        Case(
            "sdof-sbc",
            "linear",
            SBC_CONFIG,
            300,
            DT,
            None,
            LINEAR_SAMPLERS,
            "SDOF (m = 1), Matérn-3/2 force, acceleration (noise sd 0.05), dt = 0.02 s; priors "
            "log-normal: c median 0.5 (σ 0.3), k 150 (0.2), σ² 1 (0.5), ℓ 0.5 (0.3)",
        ),
        Case(
            "sdof-T2000",
            "linear",
            COVERAGE_CONFIG,
            2_000,
            DT,
            COVERAGE_TRUTH,
            LINEAR_SAMPLERS,
            "as sdof-sbc, truth c = 0.5, k = 158, σ² = 1, ℓ = 0.5; weak log-normal priors: c median 0.5 "
            "(σ 1), k 150 (0.5), σ² 1 (2), ℓ 1 (1)",
        ),
        Case("sdof-T20000", "linear", COVERAGE_CONFIG, 20_000, DT, COVERAGE_TRUTH, LINEAR_SAMPLERS, "as sdof-T2000"),
        duffing,
        *(
            dataclasses.replace(
                duffing,
                name=f"duffing-sbc-{name}",
                config={**DUFFING_SBC_CONFIG, "force": {**DUFFING_SBC_CONFIG["force"], "kernel": name}},
                description=f"as duffing-sbc, Matérn-{order} force",
                quick=False,
            )
            for name, order in (("matern12", "1/2"), ("matern52", "5/2"), ("matern72", "7/2"))
        ),
        dataclasses.replace(
            duffing,
            name="duffing-sbc-params",
            config={
                **DUFFING_SBC_CONFIG,
                "system": {
                    **DUFFING_SBC_CONFIG["system"],
                    "c": _lognormal(0.5, 0.3, 0.5),
                    "k3": _lognormal(1000.0, 0.3, 1000.0),
                },
            },
            samplers=NONLINEAR_SAMPLERS,
            description="as duffing-sbc, the damping c and cubic stiffness k3 inferred too (log-normal priors: "
            "c median 0.5 (σ 0.3), k3 1000 (0.3))",
            quick=False,
        ),
        Case(
            "bouc-wen-sbc-params",
            "duffing",
            BOUC_WEN_SBC_CONFIG,
            65,
            1.0 / 750.0,
            None,
            NONLINEAR_SAMPLERS,
            "Bouc-Wen benchmark oscillator (m = 2, c = 10, k = 5e4, beta = 800, nu = 1) at 750 Hz, alpha and "
            "gamma inferred (alpha log-normal median 5e4 (σ 0.2), gamma normal -1100 ± 300), Matérn-1/2 force "
            "(σ² log-normal median 2500 (0.5), ℓ 0.01 s (0.3)), displacement (noise sd 2e-5 m) and acceleration "
            "(0.3 m/s²), from rest in a virgin state (`[initial]` sds 1e-5 m, 1e-3 m/s, 0.3 N); records from "
            "pgas's own discrete model as duffing-sbc",
            quick=False,
        ),
        Case(
            "bouc-wen-sbc-params-default-start",
            "duffing",
            {k: v for k, v in BOUC_WEN_SBC_CONFIG.items() if k != "initial"},
            65,
            1.0 / 750.0,
            None,
            ("pgas",),
            "as bouc-wen-sbc-params, with the CLI's default initial prior (no `[initial]`: the hysteretic "
            "force's sd 14.7 N at the force's median variance, straddling the |r| kink), the records drawn from it",
            quick=False,
        ),
        *(
            Case(
                f"bouc-wen-sbc-default-start-{kernel}",
                "duffing",
                {
                    **{k: v for k, v in BOUC_WEN_SBC_CONFIG.items() if k != "initial"},
                    "system": {**BOUC_WEN_SBC_CONFIG["system"], "alpha": 5.0e4, "gamma": -1100.0},
                    "force": {**BOUC_WEN_SBC_CONFIG["force"], "kernel": kernel},
                },
                65,
                1.0 / 750.0,
                None,
                ("pgas",),
                f"as bouc-wen-sbc-params-default-start with the oscillator known (alpha 5e4, gamma -1100) and a "
                f"Matérn-{order} force: the start-up and profile moves run (they are off where system "
                "parameters are sampled), the hysteretic force's start r0 drawn from the default prior",
                quick=False,
            )
            for kernel, order in (("matern12", "1/2"), ("matern32", "3/2"), ("matern52", "5/2"), ("matern72", "7/2"))
        ),
        *(
            dataclasses.replace(
                duffing,
                name=name,
                config={
                    **DUFFING_SBC_CONFIG,
                    "force": {
                        "kernel": kernel,
                        "variance": [_lognormal(0.5, 0.5, 0.5), _lognormal(1.0, 0.5, 1.0)],
                        "lengthscale": [2.0, _lognormal(0.3, 0.3, 0.3)],
                    },
                },
                description=description,
                quick=False,
            )
            for name, kernel, description in (
                (
                    "duffing-sbc-sum",
                    "matern12 + matern52",
                    "as duffing-sbc, a kernel sum: a slow Matérn-1/2 term (ℓ 2 s fixed, σ² median 0.5 (0.5)) "
                    "and a Matérn-5/2 one (σ² median 1 (0.5), ℓ 0.3 s (0.3)), both variances and the second "
                    "lengthscale inferred",
                ),
                (
                    "duffing-sbc-sum-smooth",
                    "matern32 + matern72",
                    "as duffing-sbc-sum with smooth terms: Matérn-3/2 (ℓ 2 s fixed) plus Matérn-7/2",
                ),
            )
        ),
        dataclasses.replace(
            duffing,
            name="duffing-sbc-acc",
            config={**DUFFING_SBC_CONFIG, "sensors": DUFFING_SBC_CONFIG["sensors"][1:]},
            samplers=NONLINEAR_SAMPLERS,
            description="as duffing-sbc, acceleration only (the smooth-force case without a displacement channel)",
            quick=False,
        ),
    ]


@dataclasses.dataclass(frozen=True)
class Study:
    case: Case
    sampler: str
    replications: int
    settings: dict

    @property
    def label(self) -> str:
        return f"{self.case.name}/{self.sampler}"


#: replications per (case kind, sampler): full, then quick
REPLICATIONS = {
    "full": {
        ("SBC", "kalman-mcmc"): 200,
        ("SBC", "kalman-nuts"): 200,
        ("coverage", "kalman-mcmc"): 100,
        ("coverage", "kalman-nuts"): 50,
        ("SBC", "pgas"): 100,
        ("SBC", "ekf"): 100,
        ("SBC", "ukf"): 100,
    },
    "quick": {
        ("SBC", "kalman-mcmc"): 20,
        ("SBC", "kalman-nuts"): 1,  # a smoke run (a second cost CI 18 s)
        ("coverage", "kalman-mcmc"): 2,
        ("coverage", "kalman-nuts"): 0,
        ("SBC", "pgas"): 1,
        ("SBC", "ekf"): 1,
        ("SBC", "ukf"): 1,
    },
}


# ----- one replicate -------------------------------------------------------------------------
class RunRecord(NamedTuple):
    """One replicate: per parameter the truth, its PIT ``u`` among thinned draws and whether each
    central interval holds it; the run's R-hat, ESS, verdict and time (``error`` if it raised)."""

    truth: dict
    u: dict
    inside: dict  # name -> {level: bool}
    r_hat: dict
    ess_bulk: dict
    thinned: int  # L_i: thinned draws the ranks were taken among
    converged: bool
    seconds: float
    info: dict
    error: str | None = None


def thin_by_ess(draws: dict, rng: np.random.Generator, L: int = SBC_DRAWS) -> tuple[dict, dict]:
    """At most ``L`` joint draws, roughly independent: every ``s``-th draw of each chain, with
    ``s`` = draws / min ESS (bulk and tail, over the parameters), then ``L`` of them at random.

    Returns the thinned draws ``{name: (L_i,)}`` and the per-parameter statistics.
    """
    from latentforce.inference.convergence import quantity_stats

    stats = quantity_stats(draws)
    chains, n = next(iter(draws.values())).shape
    ess = min(min(s["ess_bulk"], s["ess_tail"]) for s in stats.values())
    stride = max(1, math.ceil(chains * n / ess)) if np.isfinite(ess) and ess > 0 else n
    pooled = {k: np.asarray(v)[:, ::stride].reshape(-1) for k, v in draws.items()}
    size = next(iter(pooled.values())).size
    if size > L:
        keep = rng.choice(size, L, replace=False)
        pooled = {k: v[keep] for k, v in pooled.items()}
    return pooled, stats


def pit(thinned: np.ndarray, truth: float, rng: np.random.Generator) -> float:
    """:math:`u = (r + V)/(L + 1)` with :math:`r` the rank of the truth among ``thinned`` (Talts et al. 2018)."""
    rank = int(np.sum(thinned < truth))
    return (rank + rng.uniform()) / (thinned.size + 1)


def central_interval(draws: np.ndarray, level: float) -> tuple[float, float]:
    a = 0.5 * (1.0 - level)
    lo, hi = np.quantile(np.asarray(draws).reshape(-1), [a, 1.0 - a])
    return float(lo), float(hi)


def replicate(study: Study, index: int, seed: int) -> RunRecord:
    """Truth (fixed or from the prior), an exact record, the sampler, and the record of the run.

    The truth and the record depend on the seed, the case and ``index`` only,
    so every sampler of a case sees the same records (a paired comparison).
    """
    import jax

    from latentforce.io.config import config_from_dict

    case = study.case
    family = FAMILIES[case.family]
    problem = config_from_dict(case.config, source=case.name)
    entropy = [seed, zlib.crc32(case.name.encode()), index]
    rng_data = np.random.default_rng(entropy)
    rng_rank = np.random.default_rng(entropy + [zlib.crc32(study.sampler.encode())])
    key_truth, key_run = jax.random.split(jax.random.key(seed))
    key_truth = jax.random.fold_in(jax.random.fold_in(key_truth, entropy[1]), index)
    key_run = jax.random.fold_in(jax.random.fold_in(key_run, entropy[1]), index)
    if case.truth is None:
        keys = jax.random.split(key_truth, len(problem.free))
        truth = {n: float(spec.prior.sample(k)) for k, (n, spec) in zip(keys, problem.free.items())}
    else:
        truth = dict(case.truth)
    y, mask, *paths = family.simulate(rng_data, problem, dict(problem.fixed, **truth), case.T, case.dt)
    latent = family.latent_names(case.T)
    for name in latent:  # "state@t": the simulated path's value
        state, t = name.split("@")
        truth[name] = float(paths[0][state][int(t)])
    t0 = time.perf_counter()
    try:
        post = family.run(key_run, study.sampler, problem, y, mask, case.dt, study.settings)
    except Exception as exc:  # a failed run is a result: counted and reported, the study goes on
        tb = traceback.format_exception(exc)
        return RunRecord(
            truth,
            {},
            {},
            {},
            {},
            0,
            False,
            time.perf_counter() - t0,
            {},
            error=f"{type(exc).__name__}: {exc} [{tb[-2].strip() if len(tb) > 1 else ''}]",
        )
    seconds = time.perf_counter() - t0
    thinned, stats = thin_by_ess(post.draws, rng_rank)
    names = list(problem.free) + latent
    return RunRecord(
        truth=truth,
        u={n: pit(thinned[n], truth[n], rng_rank) for n in names},
        inside={
            n: {lv: bool(lo <= truth[n] <= hi) for lv in LEVELS for lo, hi in [central_interval(post.draws[n], lv)]}
            for n in names
        },
        r_hat={n: stats[n]["r_hat"] for n in names},
        ess_bulk={n: stats[n]["ess_bulk"] for n in names},
        thinned=int(next(iter(thinned.values())).size),
        converged=bool(post.convergence.get("converged", False)),
        seconds=seconds,
        info=post.info,
    )


# ----- summaries ---------------------------------------------------------------------------------
def uniformity(u: np.ndarray, bins: int) -> tuple[float, float, np.ndarray]:
    """``(chi-square p, KS p, counts)`` of ``u`` against U(0, 1), ``bins`` equal bins for the chi-square."""
    from scipy import stats

    counts = np.histogram(u, bins=bins, range=(0.0, 1.0))[0]
    chi2_p = float(stats.chisquare(counts).pvalue) if u.size else float("nan")
    ks_p = float(stats.kstest(u, "uniform").pvalue) if u.size else float("nan")
    return chi2_p, ks_p, counts


def sbc_bins(n: int) -> int:
    """Bins of the rank histogram: about 5 or more expected per bin, between 2 and 20."""
    return int(min(20, max(2, n // 5)))


def summarise(study: Study, records: list[RunRecord]) -> dict:
    names = _free_names(study.case)
    ok = [r for r in records if r.error is None]
    n = len(ok)
    out = {
        "study": study,
        "runs": len(records),
        "ok": n,
        "errors": [r.error for r in records if r.error],
        "converged": float(np.mean([r.converged for r in ok])) if ok else float("nan"),
        "seconds": [r.seconds for r in records],
        "params": {},
        "thinned_short": int(sum(r.thinned < SBC_DRAWS for r in ok)),
        "info": _info_summary(ok),
    }
    bins = sbc_bins(n)
    for name in names:
        p = {
            "coverage": {lv: float(np.mean([r.inside[name][lv] for r in ok])) if ok else float("nan") for lv in LEVELS},
            "r_hat": float(np.median([r.r_hat[name] for r in ok])) if ok else float("nan"),
            "ess": float(np.median([r.ess_bulk[name] for r in ok])) if ok else float("nan"),
        }
        if study.case.kind == "SBC" and ok:
            u = np.array([r.u[name] for r in ok])
            p["chi2_p"], p["ks_p"], p["counts"] = uniformity(u, bins)
        out["params"][name] = p
    return out


def _free_names(case: Case) -> list[str]:
    """The ranked quantities: the free parameters, then the family's latent ones."""
    from latentforce.io.config import config_from_dict

    free = list(config_from_dict(case.config, source=case.name).free)
    return free + FAMILIES[case.family].latent_names(case.T)


def _info_summary(records: list[RunRecord]) -> dict:
    out = {}
    for key in (
        "acceptance",
        "steps",
        "draws_per_chain",
        "switch_rate",
        "smoother_acceptance",
        "joint_acceptance",
        "system_acceptance",
    ):
        vals = [r.info[key] for r in records if r.info.get(key) is not None]
        if vals:
            out[key] = float(np.median(vals))
    divergences = [r.info["divergences"] for r in records if r.info.get("divergences") is not None]
    if divergences:
        out["divergences"] = int(np.sum(divergences))
    out["multimodal"] = int(sum(r.info.get("modes", 1) > 1 for r in records))
    return out


# ----- the report -----------------------------------------------------------------------------
def fmt(x: float, digits: int = 3) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def coverage_cell(p: float, level: float, n: int) -> str:
    if n == 0 or not np.isfinite(p):
        return "–"
    sd = math.sqrt(level * (1.0 - level) / n)
    text = f"{p:.2f} ± {sd:.2f}"
    return f"**{text}**" if abs(p - level) > FLAG_SD * sd else text


def p_cell(p: float | None) -> str:
    if p is None:
        return "–"
    return f"**{p:.3f}**" if p < FLAG_P else f"{p:.3f}"


def sparkline(counts: np.ndarray) -> str:
    top = max(int(np.max(counts)), 1)
    return "".join(SPARK[min(len(SPARK) - 1, int(round(c / top * (len(SPARK) - 1))))] for c in counts)


def table(summaries: list[dict]) -> list[str]:
    lines = [
        "| case | sampler | T | runs | param | cover 50 % | cover 90 % | SBC χ² p | SBC KS p | "
        "ranks | converged | R-hat (median) | bulk ESS (median) | s/run (first) |",
        "|---|---|---:|---:|---|---:|---:|---:|---:|---|---:|---:|---:|---:|",
    ]
    for s in summaries:
        study = s["study"]
        seconds = s["seconds"]
        first = True
        for name, p in s["params"].items():
            study_cells = (
                [
                    study.case.name,
                    study.sampler,
                    f"{study.case.T:,}",
                    f"{s['ok']}" + (f" (+{s['runs'] - s['ok']} failed)" if s["runs"] > s["ok"] else ""),
                ]
                if first
                else ["", "", "", ""]
            )
            run_cells = [f"{s['converged']:.2f}" if np.isfinite(s["converged"]) else "–"] if first else [""]
            time_cells = (
                [
                    f"{np.median(seconds[1:] if len(seconds) > 1 else seconds):.1f} ({seconds[0]:.1f})"
                    if seconds
                    else "–"
                ]
                if first
                else [""]
            )
            lines.append(
                "| "
                + " | ".join(
                    study_cells
                    + [
                        LABELS.get(name, name),
                        coverage_cell(p["coverage"][0.5], 0.5, s["ok"]),
                        coverage_cell(p["coverage"][0.9], 0.9, s["ok"]),
                        p_cell(p.get("chi2_p")),
                        p_cell(p.get("ks_p")),
                        f"`{sparkline(p['counts'])}`" if "counts" in p else "–",
                    ]
                    + run_cells
                    + [fmt(p["r_hat"], 4), fmt(p["ess"], 3)]
                    + time_cells
                )
                + " |"
            )
            first = False
    return lines


def histograms(summaries: list[dict]) -> list[str]:
    lines = []
    for s in summaries:
        if s["study"].case.kind != "SBC" or not s["ok"]:
            continue
        for name, p in s["params"].items():
            counts = p["counts"]
            expected = s["ok"] / counts.size
            lines.append(
                f"{s['study'].label}, {LABELS.get(name, name)}: N = {s['ok']}, {counts.size} bins of u, "
                f"expected {expected:.1f} per bin (χ² p = {p['chi2_p']:.3f}, KS p = {p['ks_p']:.3f})"
            )
            scale = max(1.0, counts.max() / 40)
            for b, c in enumerate(counts):
                lo, hi = b / counts.size, (b + 1) / counts.size
                lines.append(f"  {lo:4.2f}-{hi:4.2f} |{'#' * int(round(c / scale)):<{int(40)}} {c}")
            lines.append("")
    return lines


def notes(summaries: list[dict]) -> list[str]:
    lines = []
    for s in summaries:
        info = s["info"]
        bits = []
        if "acceptance" in info:
            bits.append(f"median acceptance {info['acceptance']:.2f}")
        if "steps" in info:
            bits.append(f"median integration steps {info['steps']:.1f}")
        if "divergences" in info:
            bits.append(f"{info['divergences']} divergences")
        if "switch_rate" in info:
            bits.append(f"median ancestor switch rate {info['switch_rate']:.2f}")
        if "smoother_acceptance" in info:
            bits.append(f"median smoother-move acceptance {info['smoother_acceptance']:.2f}")
        if "joint_acceptance" in info:
            bits.append(f"median joint-move acceptance {info['joint_acceptance']:.2f}")
        if "system_acceptance" in info:
            bits.append(f"median system-move acceptance {info['system_acceptance']:.2f}")
        if "draws_per_chain" in info:
            bits.append(f"median draws per chain {info['draws_per_chain']:.0f}")
        if info.get("multimodal"):
            bits.append(f"{info['multimodal']} runs found more than one mode")
        if s["study"].case.kind == "SBC" and s["thinned_short"]:
            bits.append(f"{s['thinned_short']} runs had fewer than {SBC_DRAWS} effective draws to rank among")
        lines.append(f"- {s['study'].label}: " + "; ".join(bits) + ".")
        for err in s["errors"]:
            lines.append(f"  - failed run: {err}")
    return lines


def report(summaries: list[dict], mode: str, seed: int, total_s: float) -> str:
    import jax

    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    case_lines = []
    for case in dict.fromkeys(s["study"].case for s in summaries):
        settings = "; ".join(
            f"{s['study'].sampler}: " + ", ".join(f"{k} {v}" for k, v in s["study"].settings.items())
            for s in summaries
            if s["study"].case is case
        )
        case_lines.append(f"- **{case.name}** ({case.kind}, T = {case.T:,}): {case.description}. {settings}.")
    sizes = sorted({len(s["params"]) for s in summaries})
    group_sizes = " to ".join(str(n) for n in sizes[:: max(1, len(sizes) - 1)])
    lines = [
        f"# Calibration of the samplers ({mode})",
        "",
        f"{datetime.datetime.now().isoformat(timespec='seconds')}; {platform.machine()}, {os.cpu_count()} cores, "
        f"load average {load}; JAX {jax.__version__} on {jax.devices()[0].platform}; NumPy {np.__version__}; "
        f"seed {seed}.",
        "",
        *case_lines,
        "",
        *table(summaries),
        "",
        f"Coverage: fraction of runs whose central 50 % / 90 % posterior interval holds the truth, ± the "
        f"binomial sd at the nominal level; **bold** when more than {FLAG_SD:g} sd off. SBC rows draw the truth "
        "from the prior, so their coverage is exactly nominal for a correct sampler; coverage rows hold the "
        "truth fixed (nominal only asymptotically). SBC p-values: uniformity of the truth's rank among "
        f"{SBC_DRAWS} ESS-thinned draws, χ² on the binned ranks and Kolmogorov-Smirnov on (r + U)/(L + 1); "
        f"**bold** below {FLAG_P}. With {group_sizes} quantities per row group, one p-value below 0.05 in "
        "a few groups is expected by chance. Ranks: the histogram of the ranks (left: truth below every draw). "
        "Converged: the sampler's own verdict (R-hat ≤ 1.01, bulk ESS ≥ target, tail ESS ≥ target/4). "
        "s/run: median seconds per run after the first (the first, in brackets, compiles).",
        "",
        "## Notes per study",
        "",
        *notes(summaries),
        "",
    ]
    hist = histograms(summaries)
    if hist:
        lines += ["## SBC rank histograms", "", "```", *hist, "```", ""]
    lines.append(f"Total time {total_s:.0f} s.")
    return "\n".join(lines) + "\n"


# ----- the command line --------------------------------------------------------------------------
def studies(
    mode: str, only: list[str] | None = None, sbc_n: int | None = None, coverage_n: int | None = None
) -> list[Study]:
    out = []
    for case in cases():
        for sampler in case.samplers:
            n = (sbc_n if case.kind == "SBC" else coverage_n) or REPLICATIONS[mode][(case.kind, sampler)]
            if n == 0 or (mode == "quick" and not case.quick):
                continue
            study = Study(case, sampler, n, SETTINGS[sampler][mode])
            if only and not any(o in f"{study.label}/{case.kind.lower()}" for o in only):
                continue
            out.append(study)
    return out


def run_study(study: Study, seed: int, log=print) -> dict:
    records = []
    for i in range(study.replications):
        rec = replicate(study, i, seed)
        records.append(rec)
        status = rec.error or (
            f"converged {rec.converged}, max R-hat {max(rec.r_hat.values()):.3f}, "
            f"min ESS {min(rec.ess_bulk.values()):.0f}, L {rec.thinned}"
        )
        log(f"  {study.label} {i + 1}/{study.replications}: {rec.seconds:.1f} s, {status}")
    return summarise(study, records)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--quick", action="store_true", help="smoke mode (< 3 min): few replications, no NUTS on the T = 20 000 case"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--only",
        action="append",
        help="run only studies whose 'case/sampler/kind' contains "
        "this (repeatable), e.g. sbc, kalman-nuts, sdof-T2000/",
    )
    parser.add_argument("--sbc-replications", type=int, default=None)
    parser.add_argument("--coverage-replications", type=int, default=None)
    parser.add_argument(
        "--compile-cache",
        type=Path,
        default=None,
        help="persistent compilation cache directory (default: a temporary one for this run)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="Markdown output (default benchmarks/results/calibration.md; calibration_quick.md with --quick)",
    )
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    mode = "quick" if args.quick else "full"
    import latentforce

    latentforce.enable_x64()  # float64; XLA's small-loop threshold before JAX starts

    started = time.perf_counter()
    from latentforce.io.config import config_from_dict

    for case in cases():  # every case's config is valid, those this mode does not run too
        config_from_dict(case.config, source=case.name)
    chosen = studies(mode, args.only, args.sbc_replications, args.coverage_replications)
    summaries = []
    from latentforce.compile import persistent_cache

    with persistent_cache(args.compile_cache):
        for study in chosen:
            print(f"{study.label} ({study.case.kind}, T = {study.case.T}, {study.replications} runs)", flush=True)
            summaries.append(run_study(study, args.seed, log=lambda s: print(s, flush=True)))
    text = report(summaries, mode, args.seed, time.perf_counter() - started)
    print(text)
    out = args.out or RESULTS_DIR / ("calibration_quick.md" if args.quick else "calibration.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(f"written {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
