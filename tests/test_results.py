"""The result folder: posterior.nc, summary.csv, summary.json and figures."""

import csv
import json
import math
import warnings

import numpy as np
import pytest
import xarray as xr

from latentforce import __version__
from latentforce.errors import LatentForceError
from latentforce.results import (
    RunResult,
    coverage,
    nmse,
    read_results,
    redraw,
    summarise_parameters,
    write_figures,
    write_results,
)

T, CHAINS, DRAWS, PATHS = 50, 2, 40, 10


def _result(method="pgas", ndof=1, nforce=1, seed=0):
    rng = np.random.default_rng(seed)
    time = np.arange(T) * 0.01
    widths = {"displacement": ndof, "velocity": ndof, "force": nforce}
    truth = {
        s: np.sin(2 * np.pi * (1 + j) * time)[:, None] * np.ones((1, w)) for j, (s, w) in enumerate(widths.items())
    }
    mean = {s: truth[s] + 0.1 * rng.standard_normal((T, w)) for s, w in widths.items()}
    sd = {s: np.full((T, w), 0.1) for s, w in widths.items()}
    sampled = method != "kalman"
    params = (
        {
            "k": 100 + rng.standard_normal((CHAINS, DRAWS)),
            "force_variance": np.exp(rng.standard_normal((CHAINS, DRAWS))),
            "force_lengthscale": 0.2 * np.exp(0.1 * rng.standard_normal((CHAINS, DRAWS))),
        }
        if sampled
        else {}
    )
    paths = (
        {s: mean[s] + 0.1 * rng.standard_normal((CHAINS, PATHS, T, w)) for s, w in widths.items()} if sampled else {}
    )
    stats = (
        {
            "accepted": rng.random((CHAINS, DRAWS)) < 0.3,
            "log_likelihood": rng.standard_normal((CHAINS, DRAWS)) - 100,
        }
        if sampled
        else {}
    )
    acc = truth["displacement"][:, 0] * 50 + 0.05 * rng.standard_normal(T)
    acc[3] = np.nan
    return RunResult(
        method=method,
        time=time,
        ndof=ndof,
        nforce=nforce,
        state_mean=mean,
        state_sd=sd,
        param_draws=params,
        path_draws=paths,
        sample_stats=stats,
        acceptance=[0.3, 0.28] if sampled else [],
        log_likelihood=-123.4,
        observed={"acc": acc},
        truth=truth,
        point_estimate={"k": 100.0} if sampled else {},
        diagnostics={"true_params": {"force_variance": 1.0, "force_lengthscale": 0.2}, "ess": [np.float64(10.0)]},
        seed=seed,
        wall_time_s=1.5,
        fixed={"m": 1.0},
    )


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "out"
    result = _result()
    write_results(out, result)
    return out, result


def _open_arviz(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import arviz as az

        return az.from_netcdf(path)


def test_posterior_nc_opens_in_arviz_and_xarray(written):
    out, result = written
    idata = _open_arviz(out / "posterior.nc")
    assert {"posterior", "observed_data", "sample_stats"} <= set(idata.groups())
    assert idata.posterior["force_variance"].dims == ("chain", "draw")
    assert idata.posterior["force"].dims == ("chain", "path_draw", "time")
    np.testing.assert_array_equal(idata.posterior["time"].values, result.time)
    assert idata.sample_stats["accepted"].dims == ("chain", "draw")
    with xr.open_datatree(out / "posterior.nc", engine="h5netcdf") as tree:
        assert tree["posterior"]["displacement"].shape == (CHAINS, PATHS, T)
        np.testing.assert_array_equal(tree["observed_data"]["acc"].values, result.observed["acc"])


def test_summary_csv(written):
    out, result = written
    with open(out / "summary.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == [
        "time",
        "displacement_mean",
        "displacement_sd",
        "velocity_mean",
        "velocity_sd",
        "force_mean",
        "force_sd",
    ]
    assert len(rows) == T + 1
    table = np.array(rows[1:], dtype=float)
    np.testing.assert_array_equal(table[:, 0], result.time)
    np.testing.assert_array_equal(table[:, 5], result.state_mean["force"][:, 0])


def test_summary_json(written):
    out, result = written
    text = (out / "summary.json").read_text()
    assert "NaN" not in text
    summary = json.loads(text)
    assert list(summary)[:4] == ["method", "log_likelihood", "parameters", "acceptance"]
    assert {"nmse", "wall_time_s", "seed", "version", "point_estimate", "fixed", "diagnostics"} <= set(summary)
    assert summary["method"] == "pgas" and summary["version"] == __version__
    assert summary["log_likelihood"] == -123.4 and summary["acceptance"] == [0.3, 0.28]
    k = summary["parameters"]["k"]
    assert set(k) == {"mean", "sd", "median", "q05", "q95", "r_hat", "ess_bulk"}
    assert abs(k["mean"] - 100) < 0.5 and k["q05"] < k["median"] < k["q95"]
    assert 0.9 < k["r_hat"] < 1.1 and k["ess_bulk"] > 20
    for state in ("displacement", "velocity", "force"):
        expected = nmse(result.truth[state], result.state_mean[state])
        assert summary["nmse"][state] == pytest.approx(expected)
    assert summary["diagnostics"]["true_params"]["force_variance"] == 1.0


def test_nmse_and_coverage_known_values():
    x = np.array([1.0, -1.0, 1.0, -1.0])  # variance 1
    assert nmse(x, x + 0.5) == pytest.approx(25.0)
    assert nmse(x, x) == 0.0
    assert math.isnan(nmse(np.ones(4), np.zeros(4)))
    assert coverage(x, x + np.array([0.0, 1.0, 2.0, 4.0]), np.ones(4), k=3.0) == 0.75


def test_single_chain_r_hat_is_null():
    summary = summarise_parameters({"k": np.random.default_rng(1).standard_normal((1, 40))})
    assert math.isnan(summary["k"]["r_hat"])


def test_figures_exist(written):
    out, _ = written
    for name in (
        "measured",
        "displacement",
        "velocity",
        "force",
        "paths",
        "traces",
        "histograms",
        "joint_hyperparameters",
    ):
        png = out / "figures" / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name


def test_no_overwrite_without_force_then_force_keeps_foreign_files(tmp_path):
    out = tmp_path / "out"
    write_results(out, _result(), figures=False)
    (out / "notes.txt").write_text("mine")
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    with pytest.raises(LatentForceError, match="--force"):
        write_results(out, _result(seed=1), figures=False)
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    write_results(out, _result(seed=1), overwrite=True, figures=False)
    assert (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "summary.json").read_text())["seed"] == 1


def test_summary_json_is_written_last_so_an_unfinished_folder_has_none(tmp_path, monkeypatch):
    """While the figures are drawn (the slowest part, where a kill left a "converged" summary beside 3 of
    9 figures) the folder holds no summary.json, a replaced run's old one included; a figure that fails
    still leaves the summary, and its error."""
    from latentforce import result_files

    out = tmp_path / "out"
    write_results(out, _result(), figures=False)
    seen = []

    def figures(out_dir, result):
        seen.append((out_dir / "summary.json").exists())
        assert (out_dir / "summary.csv").exists() and (out_dir / "posterior.nc").exists()
        raise RuntimeError("a figure failed")

    monkeypatch.setattr(result_files, "write_figures", figures)
    with pytest.raises(RuntimeError, match="a figure failed"):
        write_results(out, _result(seed=1), overwrite=True)
    assert seen == [False]
    assert json.loads((out / "summary.json").read_text())["seed"] == 1


def test_read_results_round_trip_and_redraw(written, tmp_path):
    out, result = written
    back = read_results(out)
    assert (back.method, back.ndof, back.nforce, back.seed) == ("pgas", 1, 1, 0)
    np.testing.assert_array_equal(back.time, result.time)
    for name, draws in result.param_draws.items():
        np.testing.assert_array_equal(back.param_draws[name], draws)
    for group in ("state_mean", "state_sd", "path_draws", "truth"):
        for state, a in getattr(result, group).items():
            np.testing.assert_array_equal(getattr(back, group)[state], a, err_msg=f"{group}[{state}]")
    np.testing.assert_array_equal(back.sample_stats["accepted"], result.sample_stats["accepted"])
    np.testing.assert_array_equal(back.observed["acc"], result.observed["acc"])
    assert back.acceptance == result.acceptance and back.point_estimate == result.point_estimate
    before = json.loads((out / "summary.json").read_text())
    redraw(out)
    after = json.loads((out / "summary.json").read_text())
    assert after == before
    with pytest.raises(LatentForceError, match="not a latentforce result folder"):
        read_results(tmp_path)


def test_mdof_result(tmp_path):
    result = _result(ndof=2, nforce=2)
    write_results(tmp_path / "mdof", result)
    with open(tmp_path / "mdof" / "summary.csv", newline="") as f:
        header = next(csv.reader(f))
    assert header[:5] == [
        "time",
        "displacement_0_mean",
        "displacement_0_sd",
        "displacement_1_mean",
        "displacement_1_sd",
    ]
    assert header[-2:] == ["force_1_mean", "force_1_sd"]
    summary = json.loads((tmp_path / "mdof" / "summary.json").read_text())
    assert set(summary["nmse"]) == {f"{s}_{i}" for s in ("displacement", "velocity", "force") for i in (0, 1)}
    with xr.open_datatree(tmp_path / "mdof" / "posterior.nc", engine="h5netcdf") as tree:
        assert tree["posterior"]["displacement"].dims == ("chain", "path_draw", "time", "dof")
        assert tree["posterior"]["force"].dims == ("chain", "path_draw", "time", "force_index")
    back = read_results(tmp_path / "mdof")
    np.testing.assert_array_equal(back.state_mean["displacement"], result.state_mean["displacement"])


def test_kalman_result(tmp_path):
    result = _result(method="kalman")
    write_results(tmp_path / "kf", result)
    idata = _open_arviz(tmp_path / "kf" / "posterior.nc")
    assert idata.posterior["force_mean"].dims == ("time",)
    summary = json.loads((tmp_path / "kf" / "summary.json").read_text())
    assert summary["parameters"] == {} and summary["acceptance"] == []
    figures = {p.name for p in (tmp_path / "kf" / "figures").iterdir()}
    assert figures == {"measured.png", "displacement.png", "velocity.png", "force.png"}
    back = read_results(tmp_path / "kf")
    assert back.param_draws == {} and back.path_draws == {}


def test_a_demo_case_draws_its_figures_in_the_helper_process(tmp_path):
    """``demos.common.figure_process``: the figures a helper process draws are the ones the
    thread would draw (same files); drawing there leaves this process's matplotlib alone."""
    from latentforce.demos.common import figure_process
    from latentforce.plots import FIGURE_NAMES

    result = _result()
    (tmp_path / "there").mkdir()
    (tmp_path / "here").mkdir()
    with figure_process() as pool:
        assert pool is not None
        pool.submit(write_figures, tmp_path / "there", result).result()
    write_figures(tmp_path / "here", result)
    there = sorted(p.name for p in (tmp_path / "there" / "figures").iterdir())
    here = sorted(p.name for p in (tmp_path / "here" / "figures").iterdir())
    assert there == here and set(here) <= set(FIGURE_NAMES) and len(here) >= 6


def test_parameter_axes_carry_their_units():
    """A storey's, an element's and a kernel term's parameter are labelled with their base key's unit;
    Bouc-Wen's beta and gamma (a unit that depends on nu) and noise levels (the sensor's) with none."""
    from latentforce.plots import _param_label

    labels = {n: _param_label(n) for n in ("k_1", "c_0", "element0_k3", "element1_alpha", "force_lengthscale_1")}
    assert labels == {
        "k_1": "k_1 [N/m]",
        "c_0": "c_0 [N s/m]",
        "element0_k3": "element0_k3 [N/m$^3$]",
        "element1_alpha": "element1_alpha [N/m]",
        "force_lengthscale_1": "force_lengthscale_1 [s]",
    }
    assert [_param_label(n) for n in ("beta", "element0_gamma", "noise_std_acc")] == [
        "beta",
        "element0_gamma",
        "noise_std_acc",
    ]


def test_scores_by_column_name_each_dof_as_nmse_does():
    """coverage_3sd and nmse_median_smoother score every column (an MDOF structure's DOFs, its forces),
    keyed as summary.json's nmse: a badly covered upper floor is no longer hidden behind DOF 0's score."""
    from latentforce.results import by_column, coverage

    t = np.linspace(0.0, 1.0, 100)
    truth = {"velocity": np.stack([t, t, t], axis=1), "force": t, "displacement": t}
    mean = {"velocity": np.stack([t, t, t + 1.0], axis=1), "force": t[:, None]}
    sd = {"velocity": np.full((100, 3), 0.1), "force": np.full((100, 1), 0.1)}
    assert by_column(coverage, truth, mean, sd) == {
        "velocity_0": 1.0,
        "velocity_1": 1.0,
        "velocity_2": 0.0,
        "force": 1.0,
    }
