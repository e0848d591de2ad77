"""The re-centred smoother move of ``benchmarks/recentred_probe.py`` (a probe, not a move of the
sampler) against exact and independent answers, so that the probe's measurements can be repeated.
Slow-marked as a whole: a benchmark probe, not code the sampler runs (41 s of the default suite on
the 2-core CI machine, 2026-12-02)."""

import importlib.util
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_smc import linear_problem
from test_smoother_move import _duffing

import latentforce  # noqa: F401
from latentforce.compile import jit
from latentforce.inference import latent, pgas_start, smoother_move
from latentforce.kernels import Matern

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "recentred_probe.py"
_spec = importlib.util.spec_from_file_location("recentred_probe", _PATH)
recentred_move = importlib.util.module_from_spec(_spec)
sys.modules["recentred_probe"] = recentred_move
_spec.loader.exec_module(recentred_move)

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("order", [1, 3])
def test_every_step_is_accepted_on_a_linear_model(order):
    """On a linear SDOF (missing samples) every expansion is the exact one, so the ratio's
    Gaussian terms cancel the target's and every step is accepted, from anywhere; the chain's
    path stays on the model (its latent whitens to the prior's size)."""
    prob = linear_problem(T=60, missing=True, kernel=Matern(order))
    pm, tr = prob["pm"], prob["tr"]
    od = latent.observation_density(pm, prob["y"], prob["mask"])
    start = pm.path(latent.gp_prior_path(jax.random.key(5), tr, 60))
    path, acc = jit(lambda k: recentred_move.recentred_move(k, pm, tr, od, start, 12))(jax.random.key(order))
    assert bool(np.all(np.asarray(acc)))
    eps = latent.whiten(tr, pm.latent(path))
    assert 0.3 < float(jnp.mean(eps**2)) < 1.5, float(jnp.mean(eps**2))


@pytest.mark.parametrize("order", [1])
def test_precision_and_log_determinant_are_the_dense_ones(order):
    """The two pieces of the ratio that the Gaussian about a path contributes, checked against
    a dense computation on a Duffing model: the quadratic form is delta^T (I + J^T R^-1 J) delta
    and the covariance recursion's log-determinant sum is log|I + J^T R^-1 J| + log|R| (J the
    Jacobian of the expanded predictions by autodiff)."""
    pm, tr, y, mask = _duffing(order, sensors=("acceleration",), T=30)
    mask = mask.at[7, 0].set(False)
    od = latent.observation_density(pm, y, mask)
    path = pgas_start.extended_kalman_smoother(pm, tr, y, mask)
    loc = recentred_move._local(pm, tr, od, path)
    T, nl = path.shape[0], pm.nl
    scale = jnp.sqrt(jnp.diagonal(od.Rinv, axis1=1, axis2=2)) * od.maskf

    def pred(e):
        x = smoother_move.linear_path(pm, loc.lin, latent.colour(tr, e.reshape(T, nl)))
        return (jnp.einsum("tij,tj->ti", loc.lin.H, x - loc.lin.centre) * scale).reshape(-1)

    J = jax.jacfwd(pred)(jnp.zeros(T * nl))
    prec = jnp.eye(T * nl) + J.T @ J
    delta = jax.random.normal(jax.random.key(1), (T, nl))
    quad = recentred_move._precision_quad(pm, tr, od, loc, delta)
    np.testing.assert_allclose(float(quad), float(delta.reshape(-1) @ prec @ delta.reshape(-1)), rtol=1e-8)
    logdet_r = jnp.sum(jnp.log(jnp.diagonal(od.R)[None, :] * od.maskf + (1.0 - od.maskf)))
    np.testing.assert_allclose(float(loc.logdet), float(jnp.linalg.slogdet(prec)[1] + logdet_r), rtol=1e-8)
