"""Blocked particle Gibbs (latentforce.inference.pgas) against exact answers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import latentforce  # noqa: F401  (enables float64)
from latentforce.inference import pgas, smc
from latentforce.inference.kalman import kalman_smoother
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.priors import LogNormal
from latentforce.systems import Duffing

from test_smc import linear_problem


@pytest.fixture(scope="module")
def linear_run():
    prob = linear_problem(T=100, missing=True)
    ks = kalman_smoother(prob["A_d"], prob["Q_d"], prob["H"], prob["pm"].R, prob["m0f"], prob["P0"],
                         prob["y"], prob["mask"])
    out = pgas.run_pgas(jax.random.key(3, impl="rbg"), prob["model"], prob["params"], {}, prob["y"], prob["mask"],
                        prob["dt"], particles=32, iterations=1200, burn_in=100, chains=4, initial=(0.0, 0.1))
    return prob, ks, out


def test_pgas_matches_kalman_smoother(linear_run):
    """Linear SDOF, fixed hyperparameters: PGAS per-time mean and sd vs the exact smoother."""
    prob, ks, out = linear_run
    km = np.asarray(ks.means)
    ksd = np.sqrt(np.asarray(jnp.diagonal(ks.covs, axis1=1, axis2=2)))
    for name, i in [("displacement", 0), ("velocity", 1), ("force", 2)]:
        mean, sd = out.state_mean[name][:, 0], out.state_sd[name][:, 0]
        nmse = np.mean((mean - km[:, i]) ** 2) / np.var(km[:, i])
        assert nmse < 0.01 * 0.2, (name, nmse)  # well under 1 %
        ratio = sd / ksd[:, i]
        assert np.mean(np.abs(ratio - 1.0)) < 0.1, (name, ratio)
        # pointwise: within a few Monte-Carlo errors (ESS >= ~500 per time point here)
        assert np.all(np.abs(mean - km[:, i]) < 6 * ksd[:, i] / np.sqrt(300)), name


def test_pgas_mixes_everywhere(linear_run):
    _, _, out = linear_run
    rhat = out.diagnostics["rhat"]
    assert len(rhat) >= 5
    assert max(rhat.values()) < 1.05, rhat  # includes t = 0
    assert min(out.diagnostics["switch_rate"]) > 0.2  # ancestor sampling is alive
    assert out.trajectories.shape[:2] == (4, 200)
    assert np.all(np.isfinite(out.log_likelihood))


def test_hyperparameter_mh_matches_grid_posterior():
    """MH on (variance, lengthscale) given a fixed GP path vs a 2-D quadrature of the posterior."""
    model = LatentForceModel(Duffing(), Matern(0), [Sensor("acceleration", 0, 0.1)])
    params = dict(m=1.0, c=0.2, k=10.0, k3=50.0, force_variance=1.0, force_lengthscale=0.5)
    pm = smc.ParticleModel(model, params, 0.05)
    free = {"force_variance": (LogNormal(0.0, 1.0), 1.0), "force_lengthscale": (LogNormal(-0.5, 1.0), 0.5)}
    hyper = pgas.Hyper(params, free)
    xf = pgas.gp_prior_path(jax.random.key(0), pm.force_transition(1.0, 0.5), 200)

    n = 20000

    @jax.jit
    def chain(key):
        x0 = jnp.asarray(smc_softplus_inv(np.array([1.0, 0.5])))

        def step(c, k):
            x, lt = c
            x, lt, _, acc = pgas.mh_step(k, hyper, pm, x, lt, jnp.array([0.15, 0.25]), xf)
            return (x, lt), (x, acc)

        _, (xs, accs) = jax.lax.scan(step, (x0, hyper.log_target(pm, x0, xf)), jax.random.split(key, n))
        return xs, accs

    xs, accs = chain(jax.random.key(1))
    theta = np.asarray(jax.nn.softplus(xs))[2000:]
    # grid in unconstrained space
    g = np.linspace(-3.0, 4.0, 161)
    G1, G2 = np.meshgrid(g, g, indexing="ij")
    X = jnp.stack([G1.ravel(), G2.ravel()], axis=1)
    lt = np.asarray(jax.jit(jax.vmap(lambda x: hyper.log_target(pm, x, xf)))(X)).reshape(G1.shape)
    w = np.exp(lt - lt.max())
    w /= w.sum()
    T1, T2 = np.log1p(np.exp(G1)), np.log1p(np.exp(G2))
    exact = np.array([np.sum(w * T1), np.sum(w * T2)])
    # Monte-Carlo error by batch means
    batches = theta.reshape(50, -1, 2).mean(axis=1)
    se = batches.std(axis=0, ddof=1) / np.sqrt(50)
    assert np.all(np.abs(theta.mean(0) - exact) < 5 * se + 1e-3 * exact), (theta.mean(0), exact, se)
    assert 0.1 < float(np.mean(accs)) < 0.8


def smc_softplus_inv(t):
    return np.log(np.expm1(t))


@pytest.mark.slow
def test_duffing_gibbs_runs_and_converges():
    """Full blocked Gibbs on a short Duffing problem: finite output, hyperparameter R-hat."""
    model = LatentForceModel(Duffing(), Matern(0), [Sensor("displacement", 0, 0.01), Sensor("acceleration", 0, 0.1)])
    params = dict(m=1.0, c=0.2, k=10.0, k3=50.0, force_variance=1.0, force_lengthscale=0.5)
    pm = smc.ParticleModel(model, params, 0.02)
    ft = pm.force_transition(1.0, 0.5)
    xf = pgas.gp_prior_path(jax.random.key(5), ft, 200)
    path = pm.mech_path(jnp.zeros(2), xf)
    y = jax.vmap(lambda x: pm._observe(x[:2], x[2:]))(path)
    y = y + jax.random.normal(jax.random.key(6), y.shape) * jnp.array([0.01, 0.1])
    free = {"force_variance": (LogNormal(0.0, 1.0), 2.0), "force_lengthscale": (LogNormal(-0.5, 1.0), 1.0)}
    out = pgas.run_pgas(jax.random.key(0, impl="rbg"), model, params, free, y, jnp.isfinite(y), 0.02,
                        particles=32, iterations=4000, burn_in=1000, state_every=2, chains=4, mh_steps=2,
                        initial=(0.0, 0.01))
    assert np.all(np.isfinite(out.state_mean["force"]))
    assert max(out.diagnostics["rhat"].values()) < 1.1, out.diagnostics["rhat"]
    force_nmse = np.mean((out.state_mean["force"][:, 0] - xf[:, 0]) ** 2) / np.var(xf[:, 0])
    assert force_nmse < 0.2
