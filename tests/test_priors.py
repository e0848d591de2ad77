"""Priors on positive parameters and the softplus map: exact answers from scipy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

import latentforce  # noqa: F401
from latentforce.compile import jit
from latentforce.priors import (
    Flat,
    Gamma,
    HalfNormal,
    LogNormal,
    Normal,
    log_jacobian_softplus,
    log_prob_unconstrained,
    prior_from_spec,
    softplus,
    softplus_inverse,
)

# (prior, scipy frozen distribution with the same density on theta > 0)
PROPER = [
    (Normal(3.0, 0.7), stats.norm(3.0, 0.7)),
    (LogNormal(0.2, 0.8), stats.lognorm(s=0.8, scale=np.exp(0.2))),
    (HalfNormal(1.5), stats.halfnorm(scale=1.5)),
    (Gamma(2.5, 4.0), stats.gamma(2.5, scale=1 / 4.0)),
]
IDS = ["normal", "lognormal", "halfnormal", "gamma"]


def _integral(f):
    # Split at 1 so quad resolves both the mass near zero and the tail.
    a, _ = integrate.quad(f, 0.0, 1.0, limit=200)
    b, _ = integrate.quad(f, 1.0, np.inf, limit=200)
    return a + b


@pytest.mark.parametrize("prior, ref", PROPER, ids=IDS)
def test_density_integrates_to_one(prior, ref):
    total = _integral(lambda t: float(jnp.exp(prior.log_prob(t))))
    # The normal prior is truncated at zero without renormalising.
    expected = ref.sf(0.0) if isinstance(prior, Normal) else 1.0
    assert total == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize("prior, ref", PROPER, ids=IDS)
def test_log_prob_matches_scipy(prior, ref):
    theta = np.array([1e-3, 0.1, 0.7, 2.0, 3.3, 10.0])
    np.testing.assert_allclose(prior.log_prob(theta), ref.logpdf(theta), rtol=1e-10)


@pytest.mark.parametrize("prior", [p for p, _ in PROPER] + [Flat()], ids=IDS + ["flat"])
def test_non_positive_is_minus_inf(prior):
    lp = prior.log_prob(jnp.array([0.0, -1.0, -1e-12]))
    assert np.all(np.isneginf(lp))
    # The gradient stays finite where the density is zero (no NaN leaks).
    g = jax.grad(lambda t: prior.log_prob(t))(-1.0)
    assert np.isfinite(g)


@pytest.mark.parametrize("prior, ref", PROPER, ids=IDS)
def test_unconstrained_density_integrates_like_constrained(prior, ref):
    expected = ref.sf(0.0) if isinstance(prior, Normal) else 1.0
    f = lambda x: float(jnp.exp(log_prob_unconstrained(prior, x)))
    a, _ = integrate.quad(f, -np.inf, 0.0, limit=200)
    b, _ = integrate.quad(f, 0.0, np.inf, limit=200)
    assert a + b == pytest.approx(expected, rel=1e-6)


def test_softplus_round_trip_extremes():
    theta = np.array([1e-8, 1e-3, 1.0, 30.0, 1e3, 1e8])
    back = softplus(softplus_inverse(theta))
    np.testing.assert_allclose(back, theta, rtol=1e-12)
    x = np.array([-40.0, -5.0, 0.0, 5.0, 40.0, 1e8])
    np.testing.assert_allclose(softplus_inverse(softplus(x)), x, rtol=1e-10)
    assert np.all(np.isfinite(softplus(np.array([-1e4, 1e4]))))


def test_log_jacobian_is_log_sigmoid():
    x = np.array([-800.0, -30.0, -1.0, 0.0, 2.0, 800.0])
    expected = -np.logaddexp(0.0, -x)
    np.testing.assert_allclose(log_jacobian_softplus(x), expected, rtol=1e-12)
    # d softplus / dx by autodiff agrees (where it is representable).
    g = jax.vmap(jax.grad(softplus))(jnp.array([-5.0, 0.0, 5.0]))
    np.testing.assert_allclose(np.log(g), log_jacobian_softplus(jnp.array([-5.0, 0.0, 5.0])), rtol=1e-12)


def test_jit_and_vmap_over_priors_and_points():
    prior = Gamma(2.0, 3.0)
    f = jit(lambda p, x: log_prob_unconstrained(p, x))
    x = jnp.linspace(-3, 3, 7)
    np.testing.assert_allclose(f(prior, x), jax.vmap(lambda xi: f(prior, xi))(x))
    # A batch of priors (vmap over its leaves), e.g. one per chain.
    batch = Gamma(jnp.array([1.0, 2.0]), jnp.array([1.0, 3.0]))
    lp = jax.vmap(lambda p: p.log_prob(0.5))(batch)
    np.testing.assert_allclose(lp, [stats.gamma(1.0).logpdf(0.5), stats.gamma(2.0, scale=1 / 3).logpdf(0.5)])
    assert float(jit(lambda x: Flat().log_prob(x))(2.0)) == 0.0


def test_prior_families_never_compare_equal():
    assert Normal(1.0, 1.0) != LogNormal(1.0, 1.0)


@pytest.mark.parametrize("prior, ref", PROPER, ids=IDS)
def test_sample_moments(prior, ref):
    draws = np.asarray(prior.sample(jax.random.key(1), (20000,)))
    assert np.all(draws > 0)
    trunc = stats.truncnorm(-3.0 / 0.7, np.inf, 3.0, 0.7) if isinstance(prior, Normal) else ref
    se = trunc.std() / np.sqrt(draws.size)
    assert abs(draws.mean() - trunc.mean()) < 5 * se


def test_flat_cannot_be_sampled():
    with pytest.raises(ValueError):
        Flat().sample(jax.random.key(0), (3,))


def test_prior_from_spec():
    assert prior_from_spec("normal", mean=1.0, sd=2.0) == Normal(1.0, 2.0)
    assert prior_from_spec("lognormal", mu=0.0, sigma=2.0) == LogNormal(0.0, 2.0)
    assert prior_from_spec("halfnormal", sd=1.0) == HalfNormal(1.0)
    assert prior_from_spec("gamma", shape=2.0, rate=1.0) == Gamma(2.0, 1.0)
    assert prior_from_spec("flat") == Flat()
    with pytest.raises(ValueError, match="valid priors"):
        prior_from_spec("cauchy", loc=0.0)
    with pytest.raises(ValueError, match="missing sd"):
        prior_from_spec("normal", mean=1.0)
    with pytest.raises(ValueError, match="unexpected scale"):
        prior_from_spec("halfnormal", sd=1.0, scale=2.0)
    with pytest.raises(ValueError, match="positive"):
        prior_from_spec("gamma", shape=2.0, rate=0.0)


def test_default_init():
    assert Normal(5.0, 1.0).default_init() == 5.0
    assert LogNormal(0.0, 1.0).default_init() == 1.0
    assert HalfNormal(2.0).default_init() == 2.0
    assert Gamma(2.0, 4.0).default_init() == 0.5
    assert Flat().default_init() is None
