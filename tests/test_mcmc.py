"""Random-walk Metropolis and kalman-mcmc against exact answers, within Monte-Carlo error."""

import arviz as az
import jax
import jax.numpy as jnp
import numpy as np
from scipy import integrate

import latentforce  # noqa: F401
from latentforce.compile import jit
from latentforce.inference import mcmc
from latentforce.inference.kalman import log_likelihood
from latentforce.inference.kalman_mcmc import linear_gaussian, make_log_posterior, run_kalman_mcmc
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.priors import Flat, LogNormal, Normal, log_prob_unconstrained
from latentforce.simulate import measure, simulate
from latentforce.systems import LinearSystem


def test_rwm_recovers_correlated_gaussian():
    mean = jnp.array([1.0, -2.0])
    cov = jnp.array([[1.0, 0.8], [0.8, 2.0]])
    prec = jnp.linalg.inv(cov)
    logdensity = lambda x: -0.5 * (x - mean) @ prec @ (x - mean)
    chains, burn, n = 4, 1500, 4000
    states = jax.vmap(lambda x: mcmc.init(x, logdensity, jnp.ones(2)))(jnp.zeros((chains, 2)) + 3.0)
    burn_fn = jit(jax.vmap(lambda k, s: mcmc.run_chain(k, s, logdensity, burn, adapt=True,
                                                          adapt_shape_at=(500, 1000), target=0.3)))
    main_fn = jit(jax.vmap(lambda k, s: mcmc.run_chain(k, s, logdensity, n, adapt=False, target=0.3)))
    keys = jax.random.split(jax.random.key(0), 2 * chains)
    states, _, _ = burn_fn(keys[:chains], states)
    _, xs, infos = main_fn(keys[chains:], states)
    xs = np.asarray(xs)
    acc = float(np.mean(np.asarray(infos.accepted)))
    assert 0.15 < acc < 0.5
    for i in range(2):
        ess = float(az.ess(xs[..., i]))
        se = np.sqrt(float(cov[i, i]) / ess)
        assert abs(xs[..., i].mean() - float(mean[i])) < 5 * se
        # variance within ~5 standard errors (se of a variance ~ var * sqrt(2 / ess))
        assert abs(xs[..., i].var() - float(cov[i, i])) < 5 * float(cov[i, i]) * np.sqrt(2 / ess)
    corr = np.corrcoef(xs[..., 0].ravel(), xs[..., 1].ravel())[0, 1]
    assert abs(corr - 0.8 / np.sqrt(2.0)) < 0.05


def test_adaptation_is_frozen_after_burn_in():
    logdensity = lambda x: -0.5 * jnp.sum(x**2)
    s = mcmc.init(jnp.zeros(1), logdensity, jnp.ones(1))
    s2, _, _ = mcmc.run_chain(jax.random.key(1), s, logdensity, 200, adapt=False)
    assert float(s2.log_scale) == float(s.log_scale)
    assert np.array_equal(np.asarray(s2.chol), np.asarray(s.chol))


def _small_problem(T=200, seed=3):
    model = LatentForceModel(LinearSystem(), Matern(1), [Sensor("displacement", 0, 0.02)])
    truth = dict(m=1.0, c=0.4, k=10.0, force_variance=2.0, force_lengthscale=0.5)
    sim = simulate(jax.random.key(seed), model, truth, T, 0.05)
    y = measure(jax.random.key(seed + 1), sim, model.sensors)
    return model, truth, y, np.ones_like(y, bool)


def test_kalman_mcmc_matches_grid_posterior_of_one_parameter():
    """Posterior of the stiffness k by MCMC vs 1-D quadrature of the exact (Kalman) posterior."""
    model, truth, y, mask = _small_problem()
    prior = Normal(12.0, 4.0)
    fixed = dict(truth)

    @jit
    @jax.vmap
    def log_post_k(k):
        params = dict(fixed, k=k)
        return (log_likelihood(*linear_gaussian(model, params, 0.05), jnp.asarray(y), jnp.asarray(mask))
                + prior.log_prob(k))

    grid = np.linspace(2.0, 20.0, 721)
    lp = np.asarray(log_post_k(jnp.asarray(grid)))
    w = np.exp(lp - lp.max())
    assert w[0] < 1e-6 and w[-1] < 1e-6  # the grid covers the posterior
    z = integrate.trapezoid(w, grid)
    mean = integrate.trapezoid(grid * w, grid) / z
    sd = np.sqrt(integrate.trapezoid((grid - mean) ** 2 * w, grid) / z)

    out = run_kalman_mcmc(jax.random.key(0), model, fixed, {"k": (prior, 12.0)}, y, mask, 0.05,
                          iterations=3000, burn_in=1000, chains=4)
    draws = out.draws["k"]
    ess = float(az.ess(draws))
    assert ess > 300
    assert abs(draws.mean() - mean) < 5 * sd / np.sqrt(ess)
    assert abs(draws.std() / sd - 1.0) < 5 * np.sqrt(1 / (2 * ess)) + 0.02
    assert float(az.rhat(draws)) < 1.05


def test_log_posterior_includes_prior_and_jacobian():
    model, truth, y, mask = _small_problem(T=50)
    priors = (Flat(), LogNormal(0.0, 1.0))
    names = ("force_variance", "force_lengthscale")
    fixed = {k: v for k, v in truth.items() if k not in names}
    logpost, loglik = make_log_posterior(model, fixed, names, priors, y, mask, 0.05)
    x = jnp.array([0.3, -0.2])
    expected = float(loglik(x)) + sum(float(log_prob_unconstrained(p, x[i])) for i, p in enumerate(priors))
    assert np.isclose(float(logpost(x)), expected, rtol=1e-12)
