"""Trajectories of a run that samples nothing (``kalman``; ``ekf``/``ukf`` at fixed parameters).

Exact answer: their draws (forward filtering, backward sampling) have the exact RTS smoother's
means and sds, for every state and virtual sensor, every Matérn order, one and two DOFs, with
missing samples. Through the CLI the paths land in ``posterior.nc`` as ``(chain, draw, time)``
and the force spectrum is estimated from them.
"""

import json

import jax
import numpy as np
import pytest
import xarray as xr
from typer.testing import CliRunner

import latentforce  # noqa: F401  (enables float64)
from latentforce.cli import app
from latentforce.inference import gaussian
from latentforce.inference.kalman_mcmc import smooth, state_moments
from latentforce.inference.mixture import PATH_BUDGET_BYTES
from latentforce.inference.smoother_draws import DRAWS, draw_count, gaussian_paths, kalman_paths
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.outputs import OutputSpec, gaussian_moments, output_matrix
from latentforce.simulate import measure, simulate
from latentforce.systems import LinearSystem

DT, T, N = 0.05, 60, 1000


def _case(order: int, ndof: int):
    if ndof == 1:
        system = LinearSystem()
        params = dict(m=1.0, c=0.4, k=10.0, force_variance=1.0, force_lengthscale=0.5)
        sensors = [Sensor("acceleration", 0, 0.1)]
        outputs = (OutputSpec("mix", displacement=(2.0,), velocity=(-0.5,), acceleration=(0.1,), force=(1.5,)),)
    else:
        system = LinearSystem(2, (1,))
        params = dict(
            M=np.eye(2),
            C=np.array([[0.6, -0.2], [-0.2, 0.4]]),
            K=np.array([[30.0, -10.0], [-10.0, 10.0]]),
            force_variance=1.0,
            force_lengthscale=0.5,
        )
        sensors = [Sensor("acceleration", 0, 0.1), Sensor("displacement", 1, 0.01)]
        outputs = (OutputSpec("drift", displacement=(-1.0, 1.0), acceleration=(0.3, 0.0)),)
    model = LatentForceModel(system, Matern(order), sensors)
    sim = simulate(jax.random.key(order), model, params, T, DT)
    y = measure(jax.random.key(10 + order), sim, model.sensors)
    mask = np.ones(y.shape, bool)
    mask[20:26, 0] = False  # missing samples
    return model, params, np.where(mask, y, np.nan), mask, outputs


def _exact(model, params, y, mask, outputs) -> dict:
    sm = smooth(model, params, np.where(mask, y, 0.0), mask, DT)
    moments = {k: (np.asarray(m), np.asarray(s)) for k, (m, s) in state_moments(model, sm.means, sm.covs).items()}
    G = output_matrix(model, outputs, params)
    mean, sd = gaussian_moments(G, sm.means, sm.covs)
    for i, o in enumerate(outputs):
        moments[o.name] = (np.asarray(mean)[:, i : i + 1], np.asarray(sd)[:, i : i + 1])
    return moments


def _agree(paths: dict, exact: dict, n: int) -> None:
    assert set(paths) == set(exact)
    for name, (mean, sd) in exact.items():
        a = paths[name]
        assert a.shape == (1, n, T, mean.shape[1]), (name, a.shape)
        draws = a[0]
        z = (draws.mean(0) - mean) / (sd / np.sqrt(n))
        assert np.max(np.abs(z)) < 5.0, (name, np.max(np.abs(z)))
        ratio = draws.std(0) / sd
        assert np.all(np.abs(ratio - 1.0) < 0.2), (name, ratio.min(), ratio.max())


@pytest.mark.parametrize(
    "order,ndof,kalman",
    [(0, 1, "auto"), (1, 1, "auto"), (2, 1, "auto"), (3, 1, "auto"), (1, 2, "auto"), (2, 1, "parallel")],
)
def test_kalman_paths_have_the_exact_smoothers_moments(order, ndof, kalman):
    """Every Matérn order, one and two DOFs, the sequential and the parallel-scan recursions."""
    model, params, y, mask, outputs = _case(order, ndof)
    paths = kalman_paths(jax.random.key(5), model, params, y, mask, DT, outputs=outputs, kalman=kalman, n=N)
    _agree(paths, _exact(model, params, y, mask, outputs), N)


@pytest.mark.parametrize("kind,order,ndof", [("ekf", 2, 1), ("ukf", 1, 2)])
def test_gaussian_paths_on_a_linear_system_have_the_exact_smoothers_moments(kind, order, ndof):
    """ekf/ukf are exact on a linear system: their draws have the Kalman smoother's moments."""
    model, params, y, mask, outputs = _case(order, ndof)
    _, smoother = gaussian.for_parameters(kind, model, DT, outputs=outputs)
    paths = gaussian_paths(jax.random.key(6), model, smoother, params, y, mask, outputs, n=N)
    _agree(paths, _exact(model, params, y, mask, outputs), N)


def test_draw_count_keeps_to_its_budgets():
    assert draw_count(1_000, 3) == DRAWS
    assert draw_count(200_000, 3) == 16  # at least 16 where the bytes allow
    for T, width in ((50_000, 3), (10**6, 40), (5 * 10**6, 200)):
        n = draw_count(T, width)
        assert n >= 1 and (n == 1 or n * T * width * 8 <= PATH_BUDGET_BYTES), (T, width, n)


CONFIG = """
[system]
type = "{system}"
m = 1.0
c = 0.4
k = 10.0
{extra}
[force]
kernel = "matern32"
variance = 1.0
lengthscale = 0.5

[[sensors]]
column = "acc"
quantity = "acceleration"
noise_std = 0.1

[inference]
method = "{method}"
seed = 3

[data]
path = "data.csv"
time_column = "time"
"""


@pytest.mark.parametrize(
    "method,system,extra", [("kalman", "linear", ""), ("ekf", "duffing", "k3 = 50.0\nsubsteps = 2")]
)
def test_a_run_that_samples_nothing_stores_drawn_trajectories(tmp_path, monkeypatch, method, system, extra):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run.toml").write_text(CONFIG.format(system=system, method=method, extra=extra))
    runner = CliRunner()
    r = runner.invoke(app, ["simulate", "run.toml", "--out", "data.csv", "--duration", "6", "--sample-rate", "40"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["estimate", "run.toml", "--out", "out"])
    assert r.exit_code == 0, r.output
    with xr.open_datatree(tmp_path / "out" / "posterior.nc", engine="h5netcdf") as tree:
        post = tree["posterior"].to_dataset()
    T = post.sizes["time"]
    for state in ("displacement", "velocity", "force"):
        assert post[state].dims == ("chain", "draw", "time") and post[state].shape == (1, DRAWS, T)
        # the smoother's marginals stay beside them, and the draws scatter about them
        mean, sd = post[f"{state}_mean"].values, post[f"{state}_sd"].values
        z = (post[state].values[0].mean(0) - mean) / (sd / np.sqrt(DRAWS))
        assert np.mean(np.abs(z) < 3.0) > 0.95
    assert (tmp_path / "out" / "figures" / "paths.png").exists()
    psd = np.genfromtxt(tmp_path / "out" / "force_psd.csv", delimiter=",", names=True)
    assert np.all(psd["psd_q05"] <= psd["psd_mean"]) and np.all(psd["psd_mean"] <= psd["psd_q95"])
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["method"] == method and summary["converged"] is True
