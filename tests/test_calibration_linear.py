"""Calibration of the linear samplers (kalman-mcmc, kalman-nuts) against exact answers.

The fast subset of ``benchmarks/calibration.py``, whose simulator and rank
statistics these tests share:

* the benchmark's record simulator against the exact second moments of the
  discrete model;
* kalman-mcmc on 20 short records whose parameters are drawn from the priors
  (simulation-based calibration, Talts et al. 2018): the central 90 %
  interval of each parameter holds the truth in a binomial fraction of the
  runs, and the truth's rank among the thinned draws is uniform;
* kalman-mcmc and kalman-nuts against a 1-D quadrature of the exact
  posterior of the stiffness, and against each other, within Monte-Carlo error.

Slow (``-m slow``): the two samplers agree on the 4-parameter posterior, and
the benchmark's SBC study of each sampler passes its uniformity tests.
"""

import importlib.util
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

import latentforce  # noqa: F401
from latentforce.compile import jit, persistent_cache
from latentforce.inference.convergence import quantity_stats
from latentforce.inference.kalman import log_likelihood
from latentforce.inference.kalman_mcmc import linear_gaussian, run_kalman_mcmc
from latentforce.inference.kalman_nuts import run_kalman_nuts
from latentforce.io.config import config_from_dict

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "calibration.py"


def _load_benchmark():
    spec = importlib.util.spec_from_file_location("calibration_benchmark", _PATH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


cal = _load_benchmark()
DT = cal.DT
SIGMAS = 4.0  # Monte-Carlo tolerances, in standard errors


@pytest.fixture(scope="module", autouse=True)
def compile_cache(tmp_path_factory):
    """Replicates share compiled programs through JAX's persistent cache (benchmark doc); restored after."""
    with persistent_cache(tmp_path_factory.mktemp("jax-cache")):
        yield


def _free(problem):
    return {n: (s.prior, s.init) for n, s in problem.free.items()}


# ----- the simulator -------------------------------------------------------------------
def test_simulated_records_have_the_exact_moments_of_the_discrete_model():
    r"""Cov(y_t, y_s) = H A^{t-s} P_0 H^T (+ R at t = s) for a stationary start (P_0 = A P_0 A^T + Q)."""
    problem = config_from_dict(cal.SBC_CONFIG)
    params = dict(problem.fixed, c=0.5, k=150.0, force_variance=1.0, force_lengthscale=0.5)
    A, Q, H, R, m0, P0 = (np.asarray(a) for a in linear_gaussian(problem.model, params, DT))
    np.testing.assert_allclose(A @ P0 @ A.T + Q, P0, rtol=1e-8, atol=1e-12 * np.abs(P0).max())
    n, T = 20_000, 4
    y = cal.simulate_discrete(np.random.default_rng(0), A, Q, H, R, m0, P0, T, records=n)[..., 0]  # (n, T)
    exact = np.array(
        [
            [(H @ np.linalg.matrix_power(A, abs(t - s)) @ P0 @ H.T)[0, 0] + R[0, 0] * (t == s) for s in range(T)]
            for t in range(T)
        ]
    )
    empirical = np.cov(y, rowvar=False)
    # sd of a sample covariance of Gaussians: sqrt((S_tt S_ss + S_ts^2) / n)
    se = np.sqrt((np.outer(np.diag(exact), np.diag(exact)) + exact**2) / n)
    assert np.all(np.abs(empirical - exact) < SIGMAS * se), (empirical - exact) / se
    assert np.all(np.abs(y.mean(axis=0)) < SIGMAS * np.sqrt(np.diag(exact) / n))


# ----- simulation-based calibration, short runs ------------------------------------------------
BASE = dict(m=1.0, c=0.5, k=150.0, force_variance=1.0, force_lengthscale=0.5)
T_SHORT = 200
# One setting for every kalman-mcmc run of the fast tests: with k the only free parameter
# and the others fixed at BASE, every such run (whatever its record) lowers to the same
# programs, compiled once and then read from the persistent cache.
MCMC_SHORT = dict(iterations=750, burn_in=250, chains=2)


def _sbc(names, n_rep, seed, run_kwargs):
    """``n_rep`` replicates: ``names`` drawn from their priors (the others at BASE), an exact
    record, kalman-mcmc; per parameter whether the central 90 % interval holds the truth, and the
    truth's PIT among the ESS-thinned draws (uniform for an exact sampler: Talts et al. 2018)."""
    problem = config_from_dict(cal.SBC_CONFIG)
    free = {n: (problem.free[n].prior, problem.free[n].init) for n in names}
    rng = np.random.default_rng(seed)
    inside = {n: [] for n in names}
    u = {n: [] for n in names}
    for i in range(n_rep):
        keys = jax.random.split(jax.random.key(seed * 1000 + i), len(names) + 1)
        truth = {n: float(problem.free[n].prior.sample(k)) for n, k in zip(names, keys[1:])}
        params = dict(BASE, **truth)
        y, mask = cal.simulate_linear(rng, problem, params, T_SHORT, DT)
        fixed = {n: v for n, v in params.items() if n not in names}
        out = run_kalman_mcmc(keys[0], problem.model, fixed, free, y, mask, DT, **run_kwargs)
        thinned, _ = cal.thin_by_ess(out.draws, rng)
        for n in names:
            lo, hi = cal.central_interval(out.draws[n], 0.9)
            inside[n].append(lo <= truth[n] <= hi)
            u[n].append(cal.pit(thinned[n], truth[n], rng))
    return inside, u


def _assert_calibrated(inside, u):
    n_rep = len(next(iter(inside.values())))
    # The 0.1 % quantile of Binomial(n_rep, 0.9): 10 of 16 (P(X < 10) = 5e-4; 3.4 sd below 14.4),
    # 13 of 20 (P(X < 13) = 4e-4).
    floor = stats.binom.ppf(1e-3, n_rep, 0.9)
    for n in inside:
        assert sum(inside[n]) >= floor, (n, sum(inside[n]), floor)
        assert stats.kstest(u[n], "uniform").pvalue > 1e-3, (n, np.round(u[n], 2))


def test_kalman_mcmc_interval_of_k_covers_truths_drawn_from_its_prior():
    """16 short records, each at a stiffness drawn from its prior: the central 90 % interval
    holds the truth in a Binomial(16, 0.9) number of runs, and the truth's PIT is uniform."""
    _assert_calibrated(*_sbc(["k"], 16, seed=1, run_kwargs=MCMC_SHORT))


@pytest.mark.slow
def test_kalman_mcmc_intervals_cover_truths_drawn_from_the_prior_all_four_free():
    """As above with k, c, force variance and lengthscale all free and drawn from their priors."""
    _assert_calibrated(*_sbc(["k", "c", "force_variance", "force_lengthscale"], 20, seed=2, run_kwargs=MCMC_SHORT))


# ----- exact 1-D posterior -------------------------------------------------------------------
def _one_parameter_problem(seed=7):
    """Only the stiffness free, the others at BASE; a record at k = 150."""
    problem = config_from_dict(cal.SBC_CONFIG)
    y, mask = cal.simulate_linear(np.random.default_rng(seed), problem, BASE, T_SHORT, DT)
    fixed = {n: v for n, v in BASE.items() if n != "k"}
    return problem, fixed, {"k": (problem.free["k"].prior, problem.free["k"].init)}, y, mask


def _quadrature(problem, fixed, prior, y, mask):
    """Posterior mean and sd of k by trapezoidal quadrature of the exact Kalman posterior."""

    @jit
    @jax.vmap
    def log_post(k):
        lg = linear_gaussian(problem.model, dict(fixed, k=k), DT)
        return log_likelihood(*lg, jnp.asarray(y), jnp.asarray(mask)) + prior.log_prob(k)

    grid = np.linspace(60.0, 300.0, 2401)
    lp = np.asarray(log_post(jnp.asarray(grid)))
    w = np.exp(lp - lp.max())
    assert w[0] < 1e-8 and w[-1] < 1e-8  # the grid covers the posterior
    z = integrate.trapezoid(w, grid)
    mean = integrate.trapezoid(grid * w, grid) / z
    return mean, np.sqrt(integrate.trapezoid((grid - mean) ** 2 * w, grid) / z)


def _moments(draws):
    """Mean, sd and their Monte-Carlo standard errors (bulk ESS; sd's se from the Gaussian approximation)."""
    ess = quantity_stats({"x": draws})["x"]["ess_bulk"]
    mean, sd = float(np.mean(draws)), float(np.std(draws))
    return mean, sd, sd / np.sqrt(ess), sd / np.sqrt(2 * ess), ess


def test_both_linear_samplers_match_the_exact_posterior_of_one_parameter():
    problem, fixed, free, y, mask = _one_parameter_problem()
    mean, sd = _quadrature(problem, fixed, free["k"][0], y, mask)
    assert sd < 0.5 * 150.0 * 0.2  # the record informs k well beyond its prior (sd about 30)
    results = {}
    for name, run, kwargs in (
        ("kalman-mcmc", run_kalman_mcmc, MCMC_SHORT),
        # one warm-up chunk and one sampling chunk: every chunk whose state types
        # differ compiles anew (the dual-averaging state turns from weakly to
        # strongly typed over its first updates), so fewer chunks compile less
        ("kalman-nuts", run_kalman_nuts, dict(iterations=300, burn_in=300, chains=2, chunk=300)),
    ):
        out = run(jax.random.key(3), problem.model, fixed, free, y, mask, DT, **kwargs)
        m, s, se_m, se_s, ess = _moments(out.draws["k"])
        assert ess > 150, (name, ess)
        assert abs(m - mean) < SIGMAS * se_m, (name, m, mean, se_m)
        assert abs(s - sd) < SIGMAS * se_s + 0.01 * sd, (name, s, sd, se_s)
        results[name] = (m, s, se_m, se_s)
    (m1, s1, e1, f1), (m2, s2, e2, f2) = results.values()
    assert abs(m1 - m2) < SIGMAS * np.hypot(e1, e2)
    assert abs(s1 - s2) < SIGMAS * np.hypot(f1, f2) + 0.01 * sd


# ----- slow: the 4-parameter posterior, and the benchmark's SBC --------------------------------------
@pytest.mark.slow
def test_nuts_and_metropolis_agree_on_the_four_parameter_posterior():
    problem = config_from_dict(cal.SBC_CONFIG)
    truth = dict(problem.fixed, c=0.5, k=150.0, force_variance=1.0, force_lengthscale=0.5)
    y, mask = cal.simulate_linear(np.random.default_rng(11), problem, truth, 300, DT)
    outs = [
        run(
            jax.random.key(5),
            problem.model,
            dict(problem.fixed),
            _free(problem),
            y,
            mask,
            DT,
            iterations=None,
            burn_in=burn,
            chains=4,
            target_ess=1000,
            max_time=300,
        )
        for run, burn in ((run_kalman_mcmc, 500), (run_kalman_nuts, 300))
    ]
    for out in outs:
        assert out.convergence["converged"], out.convergence
    for n in problem.free:
        (m1, s1, e1, f1, _), (m2, s2, e2, f2, _) = (_moments(out.draws[n]) for out in outs)
        assert abs(m1 - m2) < SIGMAS * np.hypot(e1, e2), (n, m1, m2)
        assert abs(s1 - s2) < SIGMAS * np.hypot(f1, f2) + 0.02 * s1, (n, s1, s2)


@pytest.mark.slow
@pytest.mark.parametrize("sampler, replications", [("kalman-mcmc", 60), ("kalman-nuts", 30)])
def test_benchmark_sbc_ranks_are_uniform(sampler, replications):
    case = next(c for c in cal.cases() if c.kind == "SBC")
    study = cal.Study(case, sampler, replications, cal.SETTINGS[sampler]["quick"])
    summary = cal.run_study(study, seed=0, log=lambda s: None)
    assert summary["ok"] == replications, summary["errors"]
    n = summary["ok"]
    for name, p in summary["params"].items():
        assert p["chi2_p"] > 1e-3 and p["ks_p"] > 1e-3, (name, p)
        for level, cover in p["coverage"].items():
            assert abs(cover - level) < SIGMAS * np.sqrt(level * (1 - level) / n), (name, level, cover)
