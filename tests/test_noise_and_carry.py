"""Inferred sensor noise and priors carried over from an earlier run's posterior.

Against exact or independent answers: the inferred noise enters the Kalman
likelihood exactly as a known one does; a sampler recovers a simulated noise
level; a carried prior reproduces the calibration run's marginal posterior
(Kolmogorov-Smirnov against its draws).
"""

import copy
import json

import arviz as az
import jax
import numpy as np
import pytest
import xarray as xr
from scipy import stats
from typer.testing import CliRunner

import latentforce  # noqa: F401
from latentforce.cli import app
from latentforce.errors import LatentForceError
from latentforce.inference.kalman import log_likelihood
from latentforce.inference.kalman_mcmc import linear_gaussian, run_kalman_mcmc
from latentforce.io.config import config_from_dict

TRUE = dict(m=1.0, c=0.5, k=158.0, force_variance=1.0, force_lengthscale=0.5)
SDOF = {
    "system": {"type": "linear", "m": 1.0, "c": 0.5, "k": 158.0},
    "force": {"kernel": "matern32", "variance": 1.0, "lengthscale": 0.5},
    "sensors": [
        {
            "column": "acc",
            "quantity": "acceleration",
            "dof": 0,
            "noise_std": {"prior": "lognormal", "mu": float(np.log(0.2)), "sigma": 1.0},
        }
    ],
    "inference": {"method": "kalman-mcmc"},
}


def _record(model, params, T, dt=0.02, seed=0):
    """An exact draw from the discrete linear-Gaussian model at ``params``."""
    A, Q, H, R, m0, P0 = (np.asarray(a) for a in linear_gaussian(model, params, dt))
    rng = np.random.default_rng(seed)
    root = np.linalg.cholesky(Q + 1e-14 * np.eye(len(Q)))
    x = np.linalg.cholesky(P0) @ rng.standard_normal(len(m0))
    xs = np.empty((T, len(m0)))
    for t in range(T):
        xs[t] = x
        x = A @ x + root @ rng.standard_normal(len(m0))
    y = xs @ H.T + rng.standard_normal((T, H.shape[0])) * np.sqrt(np.diag(R))
    return y, np.ones(y.shape, bool)


# ----- inferred noise --------------------------------------------------------
def test_an_inferred_noise_enters_the_likelihood_as_a_known_one_does():
    problem = config_from_dict(SDOF)
    assert list(problem.free) == ["noise_std_acc"]
    known = copy.deepcopy(SDOF)
    known["sensors"][0]["noise_std"] = 0.07
    known["inference"]["method"] = "kalman"
    fixed_model = config_from_dict(known).model
    y, mask = _record(fixed_model, TRUE, 200)
    ll_known = log_likelihood(*linear_gaussian(fixed_model, TRUE, 0.02), y, mask)
    ll_param = log_likelihood(*linear_gaussian(problem.model, {**TRUE, "noise_std_acc": 0.07}, 0.02), y, mask)
    assert float(ll_param) == pytest.approx(float(ll_known), rel=1e-13)
    # ... and is a parameter: another value gives another likelihood
    ll_other = log_likelihood(*linear_gaussian(problem.model, {**TRUE, "noise_std_acc": 0.2}, 0.02), y, mask)
    assert abs(float(ll_other) - float(ll_known)) > 1.0


def test_an_inferred_noise_keeps_its_channels_unit():
    """With the channel in mm/s^2 the data are converted to SI but the noise parameter (and
    its prior) stay in mm/s^2: R uses noise_std_acc * 1e-3."""
    from latentforce.io.channels import noise_in_si
    from latentforce.io.data import Dataset
    from latentforce.io.units import resolve_unit

    problem = config_from_dict(SDOF)
    unit = resolve_unit("acceleration", "mm/s^2", None, who="sensor 'acc'", where="")
    dataset = Dataset(
        time=np.arange(3) * 0.02,
        dt=0.02,
        values=np.zeros((3, 1)),
        mask=np.ones((3, 1), bool),
        columns=["acc"],
        truth={},
        units={"acc": unit},
    )
    model = noise_in_si(problem, dataset).model
    assert model.sensors[0].noise_scale == pytest.approx(1e-3)
    R = np.asarray(model.noise_covariance({"noise_std_acc": 70.0}))
    assert R[0, 0] == pytest.approx(0.07**2, rel=1e-12)


def test_kalman_mcmc_recovers_a_simulated_noise_level():
    problem = config_from_dict(SDOF)
    true_sd = 0.05
    y, mask = _record(problem.model, {**TRUE, "noise_std_acc": true_sd}, 1500, seed=3)
    free = {n: (s.prior, s.init) for n, s in problem.free.items()}
    out = run_kalman_mcmc(
        jax.random.key(0),
        problem.model,
        dict(problem.fixed),
        free,
        y,
        mask,
        0.02,
        iterations=600,
        burn_in=300,
        chains=2,
    )
    draws = np.asarray(out.draws["noise_std_acc"]).ravel()
    mean, sd = draws.mean(), draws.std()
    # started at the prior's median, 0.2, four times the truth
    assert abs(mean - true_sd) < 4 * sd, (mean, sd)
    assert sd < 0.15 * true_sd, sd


def test_noise_config_errors_name_the_sensor():
    d = copy.deepcopy(SDOF)
    d["sensors"].append(
        {"column": "acc-1", "quantity": "acceleration", "dof": 0, "noise_std": {"prior": "halfnormal", "sd": 0.1}}
    )
    d["sensors"].append(
        {"column": "acc_1", "quantity": "displacement", "dof": 0, "noise_std": {"prior": "halfnormal", "sd": 0.1}}
    )
    with pytest.raises(LatentForceError, match=r"\[\[sensors\]\]\[2\]\.noise_std: columns 'acc-1' and 'acc_1'"):
        config_from_dict(d)
    d = copy.deepcopy(SDOF)
    d["sensors"][0]["noise_std"] = 0.0
    with pytest.raises(LatentForceError, match="noise standard deviation of column 'acc' must be positive"):
        config_from_dict(d)
    d["sensors"][0]["noise_std"] = {"prior": "halfnormal", "sd": 0.1}
    d["system"]["type"] = "duffing"
    d["system"]["k3"] = 1.0
    d["inference"]["method"] = "pgas"  # pgas infers a noise level too (tests/test_pgas_noise.py)
    assert list(config_from_dict(d).free) == ["noise_std_acc"]


# ----- carried posterior -------------------------------------------------------
CALIB = """
[data]
path = "data.csv"

[system]
type = "linear"
m = 1.0
c = {{ prior = "lognormal", mu = -0.7, sigma = 1.0, init = 0.5 }}
k = {{ prior = "lognormal", mu = 2.3, sigma = 1.0, init = 10.0 }}

[force]
kernel = "matern32"
variance = 2.0
lengthscale = 0.5

[[sensors]]
column = "acc"
quantity = "acceleration"
noise_std = 0.05

[[sensors]]
column = "disp"
quantity = "displacement"
noise_std = 0.002

[inference]
method = "kalman-mcmc"
iterations = {iterations}
burn_in = 200
chains = 2
"""


@pytest.fixture(scope="module")
def calibration(tmp_path_factory):
    """A finished kalman-mcmc run (c, k inferred) written through the CLI."""
    root = tmp_path_factory.mktemp("carry")
    (root / "calib.toml").write_text(CALIB.format(iterations=600))
    sim = CALIB.format(iterations=600).replace('{ prior = "lognormal", mu = -0.7, sigma = 1.0, init = 0.5 }', "0.4")
    sim = sim.replace('{ prior = "lognormal", mu = 2.3, sigma = 1.0, init = 10.0 }', "10.0")
    (root / "sim.toml").write_text(sim.replace('"kalman-mcmc"', '"kalman"'))
    runner = CliRunner()
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(root)
        r = runner.invoke(app, ["simulate", "sim.toml", "--out", "data.csv", "--duration", "20", "--sample-rate", "20"])
        assert r.exit_code == 0, r.output
        r = runner.invoke(app, ["estimate", "calib.toml", "--out", "calib"])
        assert r.exit_code == 0, r.output
    return root


def test_a_carried_prior_is_the_calibration_marginal(calibration):
    d = {
        "system": {
            "type": "linear",
            "m": 1.0,
            "c": {"prior": "posterior", "from": "calib"},
            "k": {"prior": "posterior", "from": "calib", "param": "k"},
        },
        "force": {"kernel": "matern32", "variance": 2.0, "lengthscale": 0.5},
        "sensors": [{"column": "acc", "quantity": "acceleration", "noise_std": 0.05}],
    }
    problem = config_from_dict(d, base_dir=calibration)
    with xr.open_datatree(calibration / "calib" / "posterior.nc") as tree:
        # every post-burn-in draw (the run stored fewer, aligned with its paths): what is carried
        assert "parameter_chains" in tree.children
        post = tree["parameter_chains"].to_dataset()
        stored = tree["posterior"].to_dataset()["k"].size
        draws = {n: np.asarray(post[n].values).ravel() for n in ("c", "k")}
        ess = {n: float(az.ess(np.asarray(post[n].values))) for n in ("c", "k")}
    assert problem.carried["[system].k"]["draws"] == draws["k"].size > stored
    for name in ("c", "k"):
        prior = problem.free[name].prior
        sample = np.asarray(prior.sample(jax.random.key(1), (4000,)))
        # the calibration's draws are autocorrelated: compare at their ESS, not their count
        # (the two-sample KS critical value at the 0.1 % level, c = 1.95)
        ks = stats.ks_2samp(sample, draws[name])
        n, m = sample.size, min(ess[name], draws[name].size)
        assert ks.statistic < 1.95 * np.sqrt((n + m) / (n * m)), (name, ks, ess[name])
        # medians agree up to the draws' skewness in the softplus space, where the fit is Gaussian
        # (median - mean ~ skewness x sd / 6; c's skewness there is about -0.8 on this record)
        x_draws, x_sample = np.log(np.expm1(draws[name])), np.log(np.expm1(sample))
        assert abs(np.median(x_sample) - np.median(x_draws)) < 0.25 * np.std(x_draws), name
        # its density integrates to one over the positive reals
        grid = np.linspace(1e-6, np.max(draws[name]) * 3, 20001)
        mass = np.trapezoid(np.exp(np.asarray(prior.log_prob(grid))), grid)
        assert mass == pytest.approx(1.0, abs=2e-3)
        x_init = np.log(np.expm1(problem.free[name].init))
        assert abs(x_init - np.median(x_draws)) < 0.25 * np.std(x_draws), name
    assert set(problem.carried) == {"[system].c", "[system].k"}
    assert problem.carried["[system].k"]["converged"] is not None


def test_a_monitoring_run_records_its_carried_priors(calibration):
    text = CALIB.format(iterations=100).replace(
        '{ prior = "lognormal", mu = -0.7, sigma = 1.0, init = 0.5 }', '{ prior = "posterior", from = "calib" }'
    )
    text = text.replace(
        '{ prior = "lognormal", mu = 2.3, sigma = 1.0, init = 10.0 }', '{ prior = "posterior", from = "calib" }'
    )
    text = text.replace('[[sensors]]\ncolumn = "disp"\nquantity = "displacement"\nnoise_std = 0.002\n', "")
    (calibration / "monitor.toml").write_text(text)
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(calibration)
        r = CliRunner().invoke(app, ["estimate", "monitor.toml", "--out", "monitor"])
    assert r.exit_code == 0, r.output
    summary = json.loads((calibration / "monitor" / "summary.json").read_text())
    carried = summary["diagnostics"]["carried_priors"]
    assert set(carried) == {"[system].c", "[system].k"}
    assert carried["[system].k"]["from"] == str((calibration / "calib").resolve())


def test_carry_errors_name_the_folder_and_the_parameters(calibration):
    base = {
        "system": {"type": "linear", "m": 1.0, "c": 0.4, "k": 10.0},
        "force": {"kernel": "matern32", "variance": 2.0, "lengthscale": 0.5},
        "sensors": [{"column": "acc", "quantity": "acceleration", "noise_std": 0.05}],
    }
    cases = [
        ({"prior": "posterior", "from": "missing"}, "does not exist"),
        ({"prior": "posterior", "from": "calib", "param": "kk"}, "sampled parameters are: c, k"),
        ({"prior": "posterior", "from": "calib", "param": "m"}, "it was fixed at 1"),
        ({"prior": "posterior", "from": "calib", "mean": 3.0}, r"unknown key .*Valid keys: prior, from"),
        ({"prior": "posterior"}, "needs from"),
    ]
    for table, words in cases:
        d = copy.deepcopy(base)
        d["system"]["k"] = table
        with pytest.raises(LatentForceError, match=words):
            config_from_dict(d, base_dir=calibration)
    (calibration / "empty").mkdir(exist_ok=True)
    d = copy.deepcopy(base)
    d["system"]["k"] = {"prior": "posterior", "from": "empty"}
    with pytest.raises(LatentForceError, match="holds no posterior.nc"):
        config_from_dict(d, base_dir=calibration)
