"""Parameters of either sign (k3, beta, gamma) under a normal prior on the whole real line: the
density and the samplers' coordinates against exact answers, the config, each sampler's draws of a
known density, and Bouc-Wen's gamma < 0 (the benchmark's -1100) inferred from data."""

import copy
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats
from test_bouc_wen import BOUC_WEN_CONFIG, simulated_record

from latentforce.errors import LatentForceError
from latentforce.inference.hyper_moves import Hyper
from latentforce.inference.kalman_mcmc import run_kalman_mcmc
from latentforce.io.config import config_from_dict
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.priors import (
    Gamma,
    LogNormal,
    Normal,
    SignedNormal,
    log_prob_coordinate,
    prior_from_spec,
    to_coordinate,
    to_value,
)
from latentforce.systems import Duffing


def test_signed_normal_is_the_normal_density_on_the_whole_line():
    prior = SignedNormal(-1100.0, 300.0)
    theta = np.array([-2500.0, -1100.0, -1.0, 0.0, 400.0])
    np.testing.assert_allclose(prior.log_prob(theta), stats.norm(-1100.0, 300.0).logpdf(theta), rtol=1e-12)
    total, _ = integrate.quad(lambda t: float(jnp.exp(prior.log_prob(t))), -np.inf, np.inf)
    assert total == pytest.approx(1.0, rel=1e-8)
    draws = np.asarray(prior.sample(jax.random.key(0), (20000,)))
    assert abs(draws.mean() + 1100.0) < 4 * 300.0 / np.sqrt(20000) and abs(draws.std() / 300.0 - 1) < 0.03
    assert prior.default_init() == -1100.0 and prior.signed and not Normal(1.0, 1.0).signed


CASES = [
    (SignedNormal(-3.0, 2.0), "softplus", (-np.inf, np.inf)),
    (SignedNormal(1e9, 3e8), "log", (-np.inf, np.inf)),
    (LogNormal(0.3, 0.7), "softplus", (0.0, np.inf)),
    (LogNormal(0.3, 0.7), "log", (0.0, np.inf)),
    (Gamma(2.0, 3.0), "log", (0.0, np.inf)),
]


@pytest.mark.parametrize("prior, positive, support", CASES, ids=lambda c: str(c)[:24])
def test_coordinates_invert_and_their_density_carries_the_jacobian(prior, positive, support):
    """``to_value`` inverts ``to_coordinate``, and the coordinate's density (Jacobian included)
    gives every interval of values the prior's own probability."""
    theta = np.asarray(prior.sample(jax.random.key(1), (7,)))
    x = to_coordinate(prior, theta, positive)
    np.testing.assert_allclose(to_value(prior, x, positive), theta, rtol=1e-12)
    lo, hi = np.quantile(np.asarray(prior.sample(jax.random.key(2), (4000,))), [0.2, 0.7])
    f = lambda v: float(jnp.exp(log_prob_coordinate(prior, v, positive)))
    in_x, _ = integrate.quad(f, float(to_coordinate(prior, lo, positive)), float(to_coordinate(prior, hi, positive)))
    in_theta, _ = integrate.quad(lambda t: float(jnp.exp(prior.log_prob(t))), lo, hi)
    assert in_x == pytest.approx(in_theta, rel=1e-7)
    if prior.signed:  # the standardised value: unit scale whatever the parameter's magnitude
        np.testing.assert_allclose(to_coordinate(prior, prior.mean + prior.sd, positive), 1.0)


def test_a_normal_prior_is_signed_only_on_a_key_of_either_sign():
    assert isinstance(prior_from_spec("normal", signed=True, mean=-1.0, sd=1.0), SignedNormal)
    assert type(prior_from_spec("normal", mean=1.0, sd=1.0)) is Normal
    assert isinstance(prior_from_spec("lognormal", signed=True, mu=0.0, sigma=1.0), LogNormal)


def _config(**system):
    d = copy.deepcopy(BOUC_WEN_CONFIG)
    d["system"].update(system)
    return config_from_dict(d, source="bw.toml")


def test_config_takes_priors_of_either_sign_on_k3_beta_gamma_and_elements():
    prob = _config(gamma={"prior": "normal", "mean": -1000.0, "sd": 500.0})
    prior, init = prob.free["gamma"]
    assert isinstance(prior, SignedNormal) and init == -1000.0
    prob = _config(beta={"prior": "normal", "mean": 0.0, "sd": 500.0, "init": -20.0})
    assert isinstance(prob.free["beta"].prior, SignedNormal) and prob.free["beta"].init == -20.0
    # any other prior kind keeps the key positive, as before
    prob = _config(gamma={"prior": "lognormal", "mu": 7.0, "sigma": 0.5})
    assert isinstance(prob.free["gamma"].prior, LogNormal)
    with pytest.raises(LatentForceError, match=r"\[system\].gamma.init.*positive"):
        _config(gamma={"prior": "lognormal", "mu": 7.0, "sigma": 0.5, "init": -1100.0})
    # a positive key's normal prior stays on the positive reals
    with pytest.raises(LatentForceError, match=r"\[system\].m.init.*positive"):
        _config(m={"prior": "normal", "mean": -2.0, "sd": 1.0})
    d = copy.deepcopy(BOUC_WEN_CONFIG)
    d["system"] = {"type": "duffing", "m": 1.0, "c": 1.0, "k": 1.0, "k3": {"prior": "normal", "mean": -5.0, "sd": 2.0}}
    assert isinstance(config_from_dict(d, source="d.toml").free["k3"].prior, SignedNormal)
    d["system"] = {
        "type": "linear",
        "masses": [1.0, 1.0],
        "dampings": [1.0, 1.0],
        "stiffnesses": [100.0, 100.0],
        "force_dofs": [1],
        "elements": [
            {"type": "bouc-wen", "dofs": [1, 0], "alpha": 10.0, "beta": 5.0, "nu": 1.0}
            | {"gamma": {"prior": "normal", "mean": -3.0, "sd": 2.0}},
            {"type": "cubic", "dofs": [0], "k3": {"prior": "normal", "mean": -1.0, "sd": 1.0}},
        ],
    }
    prob = config_from_dict(d, source="f.toml")
    assert isinstance(prob.free["element0_gamma"].prior, SignedNormal)
    assert isinstance(prob.free["element1_k3"].prior, SignedNormal)


def test_pgas_coordinates_of_a_signed_system_parameter():
    """pgas's joint coordinates: log for the hyperparameters and positive system parameters, the
    standardised value for a signed one; their prior density carries the Jacobian."""
    free = {
        "force_variance": (LogNormal(0.0, 1.0), 2.0),
        "k3": (SignedNormal(-50.0, 20.0), -40.0),
        "c": (Gamma(2.0, 1.0), 1.5),
    }
    hyper = Hyper({"force_variance": 1.0, "force_lengthscale": 0.1}, free, ("m", "c", "k", "k3"))
    assert hyper.joint_names == ("force_variance", "c", "k3")
    theta = np.array([2.0, 1.5, -40.0])
    x = hyper.joint_coordinates(theta)
    np.testing.assert_allclose(x, [np.log(2.0), np.log(1.5), 0.5], rtol=1e-12)
    np.testing.assert_allclose(hyper.joint_values(x), theta, rtol=1e-12)
    assert float(hyper.system_values(x[1:])["k3"]) == pytest.approx(-40.0)
    expected = (
        stats.lognorm(s=1.0).logpdf(2.0) + np.log(2.0) + stats.gamma(2.0).logpdf(1.5) + np.log(1.5)
    ) + stats.norm.logpdf(0.5)
    assert float(hyper.joint_log_prior(x)) == pytest.approx(expected, rel=1e-12)
    with pytest.raises(ValueError, match="positive"):
        Hyper({"force_variance": 1.0, "force_lengthscale": 0.1}, {"c": (Gamma(2.0, 1.0), -1.0)}, ("c",))


def test_random_walk_over_a_signed_and_a_positive_prior_draws_the_prior():
    """With a flat likelihood the random-walk sampler (kalman-mcmc, ekf, ukf) must return the
    priors themselves: a signed normal of a large magnitude and a log-normal, both in their
    coordinates (starts, proposal scales, Jacobians and the map back all exercised)."""
    model = LatentForceModel(Duffing(), Matern(0), [Sensor("acceleration", 0, 1.0)])
    fixed = dict(m=1.0, c=1.0, k=1.0, force_variance=1.0, force_lengthscale=1.0)
    free = {"k3": (SignedNormal(-2e4, 5e3), -2e4), "c": (LogNormal(0.0, 0.5), 1.0)}
    fixed.pop("c")
    out = run_kalman_mcmc(
        jax.random.key(3),
        model,
        fixed,
        free,
        np.zeros((8, 1)),
        np.ones((8, 1), dtype=bool),
        0.01,
        iterations=4000,
        burn_in=1000,
        chains=4,
        loglik=lambda params, y, mask: jnp.zeros(()),
    )
    k3, c = np.ravel(out.draws["k3"]), np.ravel(out.draws["c"])
    ess = 16000 / 20  # a conservative effective size for the random walk's autocorrelation
    assert abs(k3.mean() + 2e4) < 4 * 5e3 / np.sqrt(ess), k3.mean()
    assert abs(k3.std() / 5e3 - 1) < 0.1 and (k3 > 0).mean() > 0  # it crosses zero
    assert abs(np.log(c).mean()) < 4 * 0.5 / np.sqrt(ess) and abs(np.log(c).std() / 0.5 - 1) < 0.1
    assert stats.kstest(k3[::20], stats.norm(-2e4, 5e3).cdf).pvalue > 1e-3


def _simulate_and_estimate(tmp_path, monkeypatch, method, inference, initial=None):
    from latentforce.demos.common import to_toml

    invoke, d = simulated_record(tmp_path, monkeypatch)
    d["system"]["gamma"] = {"prior": "normal", "mean": 0.0, "sd": 2000.0, "init": 500.0}
    d["inference"] = {"method": method, **inference}
    if initial is not None:
        d["initial"] = initial
    (tmp_path / "est.toml").write_text(to_toml(d))
    res = invoke(["estimate", "est.toml", "--out", "res"])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "res" / "summary.json").read_text())
    return summary["parameters"]["gamma"], summary


@pytest.mark.parametrize("method", ["ekf", "ukf"])
def test_gaussian_methods_infer_the_benchmarks_negative_gamma(tmp_path, monkeypatch, method):
    """The Noel-Schoukens benchmark's gamma = -1100 from a 0.4 s record (acceleration and
    displacement, 1 % noise), its prior N(0, 2000^2) centred on zero and started at +500."""
    gamma, summary = _simulate_and_estimate(
        tmp_path, monkeypatch, method, {"iterations": 1500, "burn_in": 500, "chains": 2}
    )
    assert abs(gamma["mean"] + 1100.0) < 4 * gamma["sd"], gamma
    assert gamma["sd"] < 2000.0 / 5 and gamma["mean"] + 3 * gamma["sd"] < 0, gamma


# slow-marked for CI's time (66 s on 2026-12-02's slow 2-core machine);
# the negative gamma through the EKF and UKF methods stays in CI
@pytest.mark.slow
def test_pgas_infers_the_benchmarks_negative_gamma(tmp_path, monkeypatch):
    """pgas moves a signed system parameter in its own coordinate (start at the filter's mode, the
    re-centred joint move, the system move with the measured motion held, values in the results):
    from +500 under N(0, 2000^2) to gamma < 0, and the chains mix, with the CLI's default initial
    state (the hysteretic force's sd 14.7 N, straddling the |r| kink). Before the system move
    (system_moves) each chain's gamma froze there (within-chain sd 3-20, R-hat 2.6 at these counts,
    3.2-3.9 in 450-620 s "auto"). Measured here (2026-11-28, each chain started on its own model,
    the system move's walk carrying r0): R-hat 1.03, ESS 134, -814 +- 172 (ekf on this record:
    -836 +- 163), truth -1100; "auto" converged in 79-129 s over three seeds (before: 118-277 s).
    With the start-up move's r0 steps but every chain on the mode's path, one chain sat 2 000-4 500
    nats below the others at gamma ~ -2 000 (R-hat 1.46): docs/nonlinear.md."""
    settings = {"iterations": 500, "burn_in": 500, "chains": 4, "particles": 16, "thin_draws": 50}
    gamma, summary = _simulate_and_estimate(tmp_path, monkeypatch, "pgas", settings)
    assert summary["method"] == "pgas"
    assert abs(gamma["mean"] + 1100.0) < 3 * gamma["sd"], gamma
    assert 100.0 < gamma["sd"] < 2000.0 / 5 and gamma["mean"] + 3 * gamma["sd"] < 0, gamma
    # mixed: not the frozen chains (R-hat 2.6-3.9, bulk ESS 4-5) of the joint move alone
    assert gamma["r_hat"] < 1.1 and gamma["ess_bulk"] > 80, gamma
    assert min(summary["diagnostics"]["acceptance_system"]) > 0.2, summary["diagnostics"]
    # the force's hyperparameters are fixed: the headline acceptance is the system move's (it read 0)
    assert summary["acceptance"] == summary["diagnostics"]["acceptance_system"]
