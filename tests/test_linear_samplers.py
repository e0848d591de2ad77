"""The linear samplers' start, adaptation, stopping rule and bounded-memory mixture.

Against exact answers: the Laplace step against Gaussians whose mode and
covariance are known; the streamed mixture against the mixture computed from
every stored smoother; the adaptation by its acceptance on a narrow posterior.
"""

import copy
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import latentforce  # noqa: F401
from latentforce.inference import laplace, mixture
from latentforce.inference.kalman import kalman_filter, rts_smoother
from latentforce.inference.kalman_mcmc import linear_gaussian, run_kalman_mcmc
from latentforce.io.config import DEFAULT_BURN_IN, config_from_dict

TRUE = dict(m=1.0, c=0.5, k=158.0, force_variance=1.0, force_lengthscale=0.5)
SDOF = {
    "system": {
        "type": "linear",
        "m": 1.0,
        "c": {"prior": "lognormal", "mu": float(np.log(0.5)), "sigma": 1.0, "init": 0.8},
        "k": {"prior": "lognormal", "mu": float(np.log(150.0)), "sigma": 0.5, "init": 120.0},
    },
    "force": {
        "kernel": "matern32",
        "variance": {"prior": "lognormal", "mu": 0.0, "sigma": 2.0, "init": 2.0},
        "lengthscale": {"prior": "lognormal", "mu": 0.0, "sigma": 1.0, "init": 0.3},
    },
    "sensors": [{"column": "acc", "quantity": "acceleration", "dof": 0, "noise_std": 0.05}],
    "inference": {"method": "kalman-mcmc"},
}


def _record(problem, T, dt=0.02, seed=0):
    """An exact draw from the discrete linear-Gaussian model at the true parameters."""
    A, Q, H, R, m0, P0 = (np.asarray(a) for a in linear_gaussian(problem.model, TRUE, dt))
    rng = np.random.default_rng(seed)
    w, V = np.linalg.eigh(Q)
    root = V * np.sqrt(np.clip(w, 0.0, None))
    w0, V0 = np.linalg.eigh(P0)
    x = V0 * np.sqrt(np.clip(w0, 0.0, None)) @ rng.standard_normal(len(m0))
    xs = np.empty((T, len(m0)))
    for t in range(T):
        xs[t] = x
        x = A @ x + root @ rng.standard_normal(len(m0))
    y = xs @ H.T + rng.standard_normal((T, H.shape[0])) * np.sqrt(np.diag(R))
    return y, np.ones(y.shape, bool), xs


def _free(problem):
    return {n: (s.prior, s.init) for n, s in problem.free.items()}


# ----- the optimiser start ------------------------------------------------------
def test_laplace_finds_the_mode_and_covariance_of_a_gaussian():
    mean = np.array([1.0, -2.0, 0.5])
    cov = np.array([[1.0, 0.3, 0.0], [0.3, 0.5, -0.005], [0.0, -0.005, 2e-4]])  # scales 70x apart
    prec = jnp.asarray(np.linalg.inv(cov))
    logdensity = lambda x: -0.5 * (x - mean) @ prec @ (x - mean)
    modes, record = laplace.find_modes(logdensity, np.array([[0.0, 0.0, 0.0], [3.0, 1.0, -1.0]]))
    assert len(modes) == 1, record
    np.testing.assert_allclose(modes[0].x, mean, atol=1e-5)
    np.testing.assert_allclose(modes[0].cov, cov, rtol=1e-4, atol=1e-9)
    assert modes[0].laplace_ok


def test_laplace_reports_two_modes_and_starts_chains_in_each():
    a, b = jnp.array([-3.0, 0.0]), jnp.array([3.0, 1.0])

    def logdensity(x):
        return jnp.logaddexp(-0.5 * jnp.sum((x - a) ** 2), -0.5 * jnp.sum((x - b) ** 2 / 0.25))

    modes, _ = laplace.find_modes(logdensity, np.array([[-2.0, 0.5], [2.0, 0.5], [-4.0, -1.0]]))
    assert len(modes) == 2
    found = sorted(m.x[0] for m in modes)
    np.testing.assert_allclose(found, [-3.0, 3.0], atol=1e-3)
    # The broad mode has 4x the Laplace mass of the narrow one (sd 1 vs 0.5 in 2-D).
    assert modes[0].x[0] < 0 and np.isclose(modes[0].log_mass - modes[1].log_mass, np.log(4.0), atol=1e-3)
    starts, which = laplace.chain_starts(jax.random.key(0), modes, 4)
    assert sorted(which.tolist()) == [0, 0, 1, 1]
    for s, w in zip(starts, which):
        assert np.sign(s[0]) == np.sign(modes[w].x[0])  # within 2 Laplace sd of its own mode


def test_a_point_where_the_optimiser_stopped_short_is_no_mode():
    """A saddle (a start on a ridge's symmetry axis stays there) is rejected and listed."""

    def logdensity(x):  # two modes at x0 = +-4 (4 tanh 16, to 1e-13), a saddle at x0 = 0
        return jnp.logaddexp(
            -0.5 * jnp.sum((x - jnp.array([4.0, 0.0])) ** 2), -0.5 * jnp.sum((x + jnp.array([4.0, 0.0])) ** 2)
        )

    # Alone, the saddle is still the best start known, and it says it is no mode.
    modes, record = laplace.find_modes(logdensity, np.array([[0.0, 0.5]]))
    assert len(modes) == 1 and not modes[0].laplace_ok and len(record["rejected"]) == 1
    modes, record = laplace.find_modes(logdensity, np.array([[0.0, 0.5], [1.0, 0.3]]))
    assert len(modes) == 1 and np.isclose(modes[0].x[0], 4.0, atol=1e-5) and modes[0].laplace_ok
    assert len(record["rejected"]) == 1 and not record["rejected"][0]["hessian_definite"]


def test_a_mode_at_a_large_coordinate_is_found_and_its_laplace_covariance_is_right():
    """A softplus coordinate is the parameter itself when that is large (a cubic stiffness of 1e9 N/m^3):
    from a start at half the mode, with a posterior sd of 3e7 beside a unit-scale coordinate, the optimiser
    reaches the mode and the Hessian's steps (a fixed 1e-4 was round-off at x = 5e8) give its covariance.
    Before both were scaled, a user sweep's ukf run stayed at k3's init (4.99999980e8 +- 129, truth 1e9)."""

    def logdensity(x):
        return -0.5 * ((x[0] - 1e9) / 3e7) ** 2 - 0.5 * ((x[1] - 0.3) / 0.2) ** 2 - 0.1 * (x[1] - 0.3) ** 4

    modes, record = laplace.find_modes(logdensity, np.array([[5e8, 0.0]]))
    (mode,) = modes
    assert mode.laplace_ok and record["rejected"] == []
    np.testing.assert_allclose(mode.x, [1e9, 0.3], rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(np.sqrt(np.diag(mode.cov)), [3e7, 0.2], rtol=1e-3)
    # a flat direction of a large coordinate gets a variance of its scale, not of 1
    cov, ok = laplace._laplace_cov(np.diag([0.0, -25.0]), laplace.coordinate_scale(np.array([5e8, 0.3])))
    assert not ok and np.allclose(np.diag(cov), [5e7**2, 0.04])


def test_the_laplace_covariance_factors_when_curvatures_span_many_decades():
    """A rough likelihood gave curvatures of 1e15-1e18 beside flat and saddle
    directions; the covariance handed to the chain starts must still factor
    (before the variance floor, 64 of these 200 failed Cholesky)."""
    rng = np.random.default_rng(0)
    for _ in range(200):
        V, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        curvature = np.array([10 ** rng.uniform(14, 18), 0.0, -(10 ** rng.uniform(-3, 0))])
        cov, _ = laplace._laplace_cov(-(V * curvature) @ V.T)
        assert np.all(np.isfinite(cov)) and np.allclose(cov, cov.T)
        np.linalg.cholesky(cov)
        # The sharply curved direction keeps a small variance.
        assert V[:, 0] @ cov @ V[:, 0] < 1e-10 * np.abs(cov).max()
    cov, ok = laplace._laplace_cov(-np.diag([4.0, 0.25]))
    assert ok and np.allclose(cov, np.diag([0.25, 4.0]))


def test_chains_start_dispersed_around_the_mode_of_a_long_record():
    """On a long record the posterior is narrow: the optimiser's mode is where the
    chains start, within a few Laplace sd, never at ``init`` (which is far off)."""
    problem = config_from_dict(SDOF)
    y, mask, _ = _record(problem, 5000)
    out = run_kalman_mcmc(
        jax.random.key(1),
        problem.model,
        dict(problem.fixed),
        _free(problem),
        y,
        mask,
        0.02,
        iterations=None,
        burn_in=500,
        chains=4,
        max_time=120,
    )
    start = out.start
    assert start["method"] == "laplace" and len(start["modes"]) == 1
    mode = np.asarray(start["modes"][0]["x"])
    sd = np.asarray(start["modes"][0]["sd"])
    # The mode is far from init in posterior sd (the chains did not start at init) ...
    x_init = np.log(np.expm1(np.array([0.8, 120.0, 2.0, 0.3])))
    assert np.max(np.abs(x_init - mode) / sd) > 20
    # ... and the posterior means sit within a few Laplace sd of the mode.
    for i, name in enumerate(out.names):
        x = np.log(np.expm1(out.draws[name]))
        assert abs(x.mean() - mode[i]) < 3 * sd[i]
        assert 0.7 < x.std() / sd[i] < 1.4  # Laplace is close on a long record
    # ---- the adaptation: the random walk's acceptance near the optimal rate on this narrow
    # posterior, and the independence steps from the Laplace fit mostly accepted and mostly chosen
    ind = out.sampler_info["independence"]
    rw = np.array(ind["random_walk_acceptance"])
    assert np.all((rw > 0.12) & (rw < 0.40)), rw
    assert np.all(np.array(ind["acceptance"]) > 0.3) and np.all(np.array(ind["share"]) > 0.5), ind
    # ---- "auto" stopped because the run converged
    assert out.convergence["converged"], out.convergence
    assert out.convergence["max_r_hat"] <= 1.01 and out.convergence["min_ess_bulk"] >= 400


def test_fixed_iterations_and_an_unconverged_auto_run_say_so():
    problem = config_from_dict(SDOF)
    y, mask, _ = _record(problem, 300, seed=4)
    out = run_kalman_mcmc(
        jax.random.key(2),
        problem.model,
        dict(problem.fixed),
        _free(problem),
        y,
        mask,
        0.02,
        iterations=30,
        burn_in=20,
        chains=2,
    )
    assert out.draws["k"].shape == (2, 30)
    assert not out.convergence["converged"]  # 30 draws cannot show an ESS of 400
    # "auto" with no time left stops after one chunk, not converged, and says why not.
    out = run_kalman_mcmc(
        jax.random.key(2),
        problem.model,
        dict(problem.fixed),
        _free(problem),
        y,
        mask,
        0.02,
        iterations=None,
        burn_in=20,
        chains=2,
        max_time=0.0,
        chunk=20,
    )
    assert out.draws["k"].shape == (2, 20)
    assert not out.convergence["converged"] and out.convergence["worst"]


def test_auto_stops_on_the_verdict_it_reports(monkeypatch):
    """An "auto" run decides to stop on the same quantities the run then reports (``finish``): the physical
    values, not the sampling coordinates, whose folded R-hat differs (an ekf run with inferred
    hyperparameters once stopped "converged" in the coordinates and reported R-hat 1.0104)."""
    from latentforce.inference import convergence, kalman_mcmc
    from latentforce.priors import LogNormal

    seen = []

    def diagnose(quantities, **kwargs):
        seen.append({k: np.array(v) for k, v in quantities.items()})
        return {"converged": True}

    monkeypatch.setattr(convergence, "diagnose", diagnose)
    rng = np.random.default_rng(0)

    def run_chunk(keys, states, start_step, adapt):
        xs = rng.standard_normal((2, 10, 1))
        return states, xs, {"accepted": np.ones((2, 10)), "logdensity": -0.5 * xs[..., 0] ** 2}

    priors = (LogNormal(0.0, 1.0),)
    _, xs, stats, _ = kalman_mcmc.sample_in_chunks(
        jax.random.key(0),
        None,
        run_chunk,
        ("k",),
        priors,
        chains=2,
        n_chunk=10,
        burn_total=10,
        iterations=None,
        target_ess=400,
        max_time=600.0,
        t0=time.perf_counter(),
    )
    assert len(seen) == 1  # stopped at the first verdict after the warm-up
    kalman_mcmc.finish(xs, stats["logdensity"], ("k",), priors, 400)
    loop, reported = seen
    assert loop.keys() == reported.keys()
    for name in loop:
        np.testing.assert_array_equal(loop[name], reported[name])
    assert not np.allclose(loop["k"], xs[..., 0])  # the physical values, not the coordinates


def test_auto_warm_up_stops_at_half_of_max_time_and_a_resumed_run_keeps_the_cut(monkeypatch, tmp_path):
    """An "auto" run whose warm-up is still adapting at half of ``max_time`` ends it at that chunk's end:
    the next chunks adapt nothing and are kept as draws, and the warm-up run is returned (not the
    configured one). A run restored from a checkpoint written after the cut keeps it. Fixed
    ``iterations`` are never cut. (The clock is the test's: it jumps when a chunk reports.)"""
    from latentforce.inference import convergence, kalman_mcmc
    from latentforce.priors import LogNormal

    class Clock:
        now = 0.0

        def perf_counter(self):
            return self.now

    clock = Clock()
    monkeypatch.setattr(kalman_mcmc, "_time", clock)
    adapted, rng = [], np.random.default_rng(0)

    def run_chunk(keys, states, start_step, adapt):
        adapted.append(bool(adapt))
        xs = rng.standard_normal((2, 10, 1))
        return states, xs, {"accepted": np.ones((2, 10)), "logdensity": -0.5 * xs[..., 0] ** 2}

    pace = {"first": 0.0, "chunk": 30.0}  # 30 s a chunk, max_time 100: the third chunk's end is past 50 s

    def progress(done, total, rate):
        clock.now = pace["first"] + pace["chunk"] * done / 10

    def sample(iterations, checkpoint=None):
        adapted.clear()
        clock.now = 0.0
        return kalman_mcmc.sample_in_chunks(
            jax.random.key(0),
            {"x": np.zeros(2)},
            run_chunk,
            ("k",),
            (LogNormal(0.0, 1.0),),
            chains=2,
            n_chunk=10,
            burn_total=100,
            iterations=iterations,
            target_ess=1e9,
            max_time=100.0,
            t0=0.0,
            progress=progress,
            checkpoint=checkpoint,
        )

    _, xs, _, warm = sample(None)
    assert warm == 20 and adapted == [True, True, False, False]  # cut at 2 chunks (60 s); 120 s > max_time
    assert xs.shape == (2, 20, 1)
    _, xs, _, warm = sample(30)
    assert warm == 100 and adapted == [True] * 10 + [False] * 3 and xs.shape == (2, 30, 1)

    class Saved:  # the checkpoint of the chunk boundary after the cut, kept in memory
        saved = None

        def save(self, sampler, loop_state):
            state = loop_state()
            if state.done == 30:
                self.saved = state

        def restore(self, sampler):
            return self.saved

    cp = Saved()
    sample(None, cp)
    assert cp.saved.extra == {"warm_up": 20}
    cp.save = lambda *a: None
    _, xs, _, warm = sample(None, cp)
    assert warm == 20 and adapted == [False] and xs.shape == (2, 20, 1)
    # past half of max_time at the first chunk (a long compile): the warm-up still runs its floor
    pace.update(first=60.0, chunk=10.0)
    _, _, _, warm = sample(None)
    assert warm == 20 == -(-convergence.WARM_UP_FLOOR * 100 // 10) * 10 and adapted[:3] == [True, True, False]


# ----- the bounded-memory mixture ----------------------------------------------------
def test_streamed_mixture_equals_the_mixture_of_every_stored_smoother():
    problem = config_from_dict(SDOF)
    y, mask, _ = _record(problem, 120, seed=5)
    mask[10:14, 0] = False
    rng = np.random.default_rng(0)
    chains, n = 2, 40
    draws = {
        "c": 0.5 * np.exp(0.2 * rng.standard_normal((chains, n))),
        "k": 158.0 * np.exp(0.02 * rng.standard_normal((chains, n))),
        "force_variance": np.exp(0.3 * rng.standard_normal((chains, n))),
        "force_lengthscale": 0.5 * np.exp(0.1 * rng.standard_normal((chains, n))),
    }
    mix = mixture.mixture_posterior(
        jax.random.key(0), problem.model, dict(problem.fixed), draws, y, mask, 0.02, thin_draws=5
    )
    per_chain, n_paths = mixture.mixture_size(120, chains, n, 5, 3)
    assert mix.n_mix == chains * per_chain and mix.paths["force"].shape == (chains, n_paths, 120, 1)
    # Every mixed draw's smoother, stored, then mixed by the law of total variance.
    idx = np.linspace(0, n - 1, per_chain).round().astype(int)

    @jax.jit
    def smoother(theta):
        A, Q, H, R, m0, P0 = linear_gaussian(problem.model, dict(problem.fixed, **theta), 0.02)
        sm = rts_smoother(A, kalman_filter(A, Q, H, R, m0, P0, jnp.asarray(np.where(mask, y, 0.0)), jnp.asarray(mask)))
        return sm.means, jnp.diagonal(sm.covs, axis1=-2, axis2=-1)

    means, variances = [], []
    for c in range(chains):
        for j in idx:
            m, v = smoother({k: draws[k][c, j] for k in draws})
            means.append(np.asarray(m))
            variances.append(np.asarray(v))
    means, variances = np.stack(means), np.stack(variances)
    mean = means.mean(0)
    sd = np.sqrt(variances.mean(0) + means.var(0))
    for name, ix in (("displacement", 0), ("velocity", 1), ("force", 2)):
        np.testing.assert_allclose(mix.moments[name][0][:, 0], mean[:, ix], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(mix.moments[name][1][:, 0], sd[:, ix], rtol=1e-9)


def test_stored_paths_stay_within_their_memory_budget(monkeypatch):
    monkeypatch.setattr(mixture, "PATH_BUDGET_BYTES", 2 * 3 * 500 * 8 * 3)  # three paths per chain
    per_chain, n_paths = mixture.mixture_size(500, 2, 1000, 200, 3)
    assert n_paths == 3 and per_chain >= 16
    # the draws mixed do not depend on the number of draws sampled once there are enough
    assert mixture.mixture_size(500, 2, 10**6, 200, 3)[0] == mixture.mixture_size(500, 2, 10**3, 200, 3)[0]
    # fewer mixed draws on long records, never fewer than 16 per chain
    assert mixture.mixture_size(200_000, 4, 10**4, 200, 3)[0] == 16


# ----- the configuration --------------------------------------------------------
def test_inference_defaults_are_auto_and_kalman_nuts_is_a_method():
    p = config_from_dict(SDOF)
    assert p.inference.iterations is None  # "auto"
    assert p.inference.target_ess == 400 and p.inference.max_time == 600
    assert p.inference.burn_in == DEFAULT_BURN_IN["kalman-mcmc"]
    d = copy.deepcopy(SDOF)
    d["inference"] = {"method": "kalman-nuts", "iterations": 300, "target_ess": 100, "max_time": 5}
    p = config_from_dict(d)
    assert (p.inference.method, p.inference.iterations, p.inference.target_ess, p.inference.max_time) == (
        "kalman-nuts",
        300,
        100,
        5,
    )
    d["inference"] = {"iterations": "forever"}
    with pytest.raises(latentforce.LatentForceError, match="iterations"):
        config_from_dict(d, source="c.toml")


# ----- the steady-state smoother of long complete records --------------------------
def _two_dof():
    d = {
        "system": {
            "type": "linear",
            "M": [[1.0, 0.0], [0.0, 2.0]],
            "C": [[0.3, -0.1], [-0.1, 0.2]],
            "K": [[200.0, -100.0], [-100.0, 100.0]],
            "force_dofs": [1],
        },
        "force": {"kernel": "matern52", "variance": 1.0, "lengthscale": 0.5},
        "sensors": [
            {"column": "a0", "quantity": "acceleration", "dof": 0, "noise_std": 0.1},
            {"column": "d1", "quantity": "displacement", "dof": 1, "noise_std": 1e-3},
        ],
    }
    return config_from_dict(d)


# two-dof under -m slow (35 s on 2026-12-02's slow 2-core machine); the sdof case stays in CI
@pytest.mark.parametrize("which", ["sdof", pytest.param("two-dof", marks=pytest.mark.slow)])
def test_steady_smoother_equals_the_full_smoother(which):
    from latentforce.inference import steady
    from latentforce.inference.kalman import sample_smoothed_trajectory

    problem = config_from_dict(SDOF) if which == "sdof" else _two_dof()
    params = dict(problem.fixed, **({} if which == "two-dof" else {n: TRUE[n] for n in problem.free}))
    A, Q, H, R, m0, P0 = linear_gaussian(problem.model, params, 0.02)
    y = np.random.default_rng(1).normal(size=(3000, H.shape[0]))
    sm = jax.jit(lambda y_: steady.steady_smoother(A, Q, H, R, m0, P0, y_, jax.random.key(0), K=1024))(y)
    filt = kalman_filter(A, Q, H, R, m0, P0, jnp.asarray(y))
    full = rts_smoother(A, filt)
    var = np.asarray(jnp.diagonal(full.covs, axis1=-2, axis2=-1))
    assert bool(sm.converged)
    np.testing.assert_allclose(sm.means, full.means, rtol=0, atol=1e-10 * float(np.abs(full.means).max()))
    np.testing.assert_allclose(sm.variances, var, rtol=1e-9)
    np.testing.assert_allclose(float(sm.log_likelihood), float(full.log_likelihood), rtol=1e-12)
    # The sampled path: standardised residuals of unit variance on average over draws,
    # as for forward filtering, backward sampling with every covariance.
    draw = jax.jit(lambda k: steady.steady_smoother(A, Q, H, R, m0, P0, jnp.asarray(y), k, K=1024).path)
    z2 = np.mean([np.mean((np.asarray(draw(jax.random.key(i))) - full.means) ** 2 / var) for i in range(8)])
    ffbs = jax.jit(lambda k: sample_smoothed_trajectory(k, A, Q, filt))
    ref = np.mean([np.mean((np.asarray(ffbs(jax.random.key(50 + i))) - full.means) ** 2 / var) for i in range(8)])
    assert abs(z2 - 1.0) < 0.15 and abs(ref - 1.0) < 0.15
    # Too short a transient is reported, not silently used.
    assert not bool(steady.steady_smoother(A, Q, H, R, m0, P0, jnp.asarray(y), K=3).converged)


def test_settling_steps_and_the_transient_they_size():
    """The filter covariance's settling steps equal a NumPy loop's count; the transient covers them."""
    from latentforce.inference import steady

    problem = config_from_dict(SDOF)
    A, Q, H, R, m0, P0 = (np.asarray(a) for a in linear_gaussian(problem.model, dict(problem.fixed, **TRUE), 0.02))
    P, steps = P0, 0
    while steps < 5000:
        P_f = P.copy()
        for i in range(H.shape[0]):
            k = P_f @ H[i] / (H[i] @ P_f @ H[i] + R[i, i])
            P_f = P_f - np.outer(k, H[i] @ P_f)
        P_next = A @ P_f @ A.T + Q
        steps += 1
        scale = np.sqrt(np.outer(np.abs(np.diag(P)), np.abs(np.diag(P))))
        if np.all(np.abs(P_next - P) <= steady.TOL * scale):
            break
        P = P_next
    got = int(jax.jit(steady.settling_steps, static_argnums=5)(A, Q, H, R, P0, 5000))
    assert 50 < steps < 5000 and abs(got - steps) <= 2, (got, steps)
    K = steady.transient_for(got, 10**5)
    assert K >= 1.25 * got and K & (K - 1) == 0
    assert steady.transient_for(got, 2 * K) is None  # too short a record for it


def test_mixture_redoes_draws_whose_transient_is_too_short(monkeypatch):
    """A transient far too short for every draw: each is redone (longer transient, then in full)
    and the mixture still equals the full smoothers'."""
    from latentforce.inference import steady

    problem = config_from_dict(SDOF)
    y, mask, _ = _record(problem, 800, seed=7)
    rng = np.random.default_rng(3)
    draws = {
        "c": 0.5 * np.exp(0.2 * rng.standard_normal((2, 8))),
        "k": 158.0 * np.exp(0.02 * rng.standard_normal((2, 8))),
        "force_variance": np.exp(0.3 * rng.standard_normal((2, 8))),
        "force_lengthscale": 0.5 * np.exp(0.1 * rng.standard_normal((2, 8))),
    }
    kw = dict(thin_draws=2, point={k: float(v[0, 0]) for k, v in draws.items()})
    monkeypatch.setattr(steady, "TRANSIENT", 200)
    monkeypatch.setattr(steady, "transient_for", lambda steps, T: 4)
    short = mixture.mixture_posterior(jax.random.key(0), problem.model, dict(problem.fixed), draws, y, mask, 0.02, **kw)
    monkeypatch.setattr(steady, "TRANSIENT", 10**6)  # never applies: the full smoother
    full = mixture.mixture_posterior(jax.random.key(0), problem.model, dict(problem.fixed), draws, y, mask, 0.02, **kw)
    for name in ("displacement", "velocity", "force"):
        np.testing.assert_allclose(short.moments[name][0], full.moments[name][0], rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(short.moments[name][1], full.moments[name][1], rtol=1e-8)


def test_streamed_mixture_on_a_long_record_uses_the_steady_smoother_exactly(monkeypatch):
    from latentforce.inference import steady

    monkeypatch.setattr(steady, "TRANSIENT", 200)
    problem = config_from_dict(SDOF)
    y, mask, _ = _record(problem, 800, seed=6)
    assert steady.applies(800, True)
    rng = np.random.default_rng(2)
    draws = {
        "c": 0.5 * np.exp(0.2 * rng.standard_normal((2, 16))),
        "k": 158.0 * np.exp(0.02 * rng.standard_normal((2, 16))),
        "force_variance": np.exp(0.3 * rng.standard_normal((2, 16))),
        "force_lengthscale": 0.5 * np.exp(0.1 * rng.standard_normal((2, 16))),
    }
    fast = mixture.mixture_posterior(
        jax.random.key(0),
        problem.model,
        dict(problem.fixed),
        draws,
        y,
        mask,
        0.02,
        thin_draws=2,
        point={k: 1.0 * v[0, 0] for k, v in draws.items()},
    )
    monkeypatch.setattr(steady, "TRANSIENT", 10**6)  # never applies: the full smoother
    full = mixture.mixture_posterior(
        jax.random.key(0),
        problem.model,
        dict(problem.fixed),
        draws,
        y,
        mask,
        0.02,
        thin_draws=2,
        point={k: 1.0 * v[0, 0] for k, v in draws.items()},
    )
    for name in ("displacement", "velocity", "force"):
        np.testing.assert_allclose(fast.moments[name][0], full.moments[name][0], rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(fast.moments[name][1], full.moments[name][1], rtol=1e-8)
    assert np.isclose(fast.point[1], full.point[1], rtol=1e-12)
