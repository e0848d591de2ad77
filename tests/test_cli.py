"""The command line end to end: simulate -> estimate -> report, and bad input."""

import json
import math
import os

import numpy as np
import pytest
from typer.testing import CliRunner

from latentforce.cli import app

runner = CliRunner()

CONFIG = """
[data]
path = "data.csv"
time_column = "time"
missing = "{missing}"

[system]
type = "linear"
m = 1.0
c = 0.4
k = 10.0

[force]
kernel = "matern32"
variance = 2.0
lengthscale = 0.5

[[sensors]]
column = "acc"
quantity = "acceleration"
dof = 0
noise_std = 0.05

[[sensors]]
column = "disp"
quantity = "displacement"
dof = 0
noise_std = 0.002

[inference]
method = "kalman"
"""


def invoke(*args):
    result = runner.invoke(app, [str(a) for a in args])
    return result.exit_code, result.output + (result.stderr if result.stderr_bytes is not None else "")


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "lf.toml").write_text(CONFIG.format(missing="error"))
    code, out = invoke("simulate", "lf.toml", "--out", "data.csv", "--duration", "10", "--sample-rate", "20")
    assert code == 0, out
    return tmp_path


def test_simulate_out_a_folder_an_extension_or_a_new_folder(workdir):
    """--out a folder or without a known extension: a clear error before simulating, the folder and
    its files untouched; in a folder not yet made: made, as estimate makes its --out's parents."""
    (workdir / "runs").mkdir()
    (workdir / "runs" / "keep.txt").write_text("mine")
    for target in ("runs", "runs.csv/"):
        if target.endswith("/"):
            (workdir / target).mkdir()
        code, out = invoke("simulate", "lf.toml", "--out", target, "--duration", "1", "--force")
        assert code == 1 and "is a folder" in out and "Traceback" not in out and "bug" not in out, out
    assert (workdir / "runs" / "keep.txt").read_text() == "mine"
    code, out = invoke("simulate", "lf.toml", "--out", "new/x.txt", "--duration", "1")
    assert code == 1 and "unknown extension '.txt'" in out and not (workdir / "new").exists(), out
    code, out = invoke("simulate", "lf.toml", "--out", "new/deep/x.csv", "--duration", "1")
    assert code == 0 and (workdir / "new" / "deep" / "x.csv").is_file(), out


def test_simulate_refuses_a_structure_that_runs_away(workdir):
    """A softening spring pushed past its turning point: the motion overflows, and simulate says so (when
    and why) and writes nothing, where it wrote a file of NaN from there on and exited 0 (user sweep 42)."""
    text = (workdir / "lf.toml").read_text().replace('type = "linear"', 'type = "duffing"')
    text = text.replace("k = 10.0", "k = 10.0\nk3 = -1.0e4").replace('method = "kalman"', 'method = "ukf"')
    (workdir / "soft.toml").write_text(text)
    code, out = invoke("simulate", "soft.toml", "--out", "soft.csv", "--duration", "10", "--sample-rate", "20")
    assert code == 1 and "grew without bound" in out and "negative k3" in out and "Traceback" not in out, out
    assert not (workdir / "soft.csv").exists()


def test_simulate_estimate_report(workdir):
    code, out = invoke("estimate", "lf.toml", "--out", "res")
    assert code == 0, out
    summary = json.loads((workdir / "res" / "summary.json").read_text())
    assert summary["method"] == "kalman" and math.isfinite(summary["log_likelihood"])
    # The exact smoother recovers the force from acceleration + displacement.
    assert summary["nmse"]["displacement"] < 1.0 and summary["nmse"]["force"] < 20.0
    header = (workdir / "res" / "summary.csv").read_text().splitlines()[0].split(",")
    assert header == [
        "time",
        "displacement_mean",
        "displacement_sd",
        "velocity_mean",
        "velocity_sd",
        "force_mean",
        "force_sd",
    ]
    assert (workdir / "res" / "figures" / "force.png").stat().st_size > 1000
    code, out = invoke("report", "res")
    assert code == 0, out


def test_existing_result_folder_is_not_overwritten(workdir):
    assert invoke("estimate", "lf.toml", "--out", "res")[0] == 0
    before = (workdir / "res" / "summary.json").read_bytes()
    code, out = invoke("estimate", "lf.toml", "--out", "res")
    assert code != 0 and "--force" in out and "Traceback" not in out
    assert (workdir / "res" / "summary.json").read_bytes() == before
    assert invoke("estimate", "lf.toml", "--out", "res", "--force")[0] == 0


def _edit(workdir, old, new, name="bad.toml"):
    text = (workdir / "lf.toml").read_text()
    assert old in text
    (workdir / name).write_text(text.replace(old, new, 1))
    return name


BAD_CONFIGS = [
    ("[system]", "[sytem]", ["sytem", "system"]),
    ("noise_std = 0.05", "noise_sd = 0.05", ["noise_sd", "noise_std"]),
    ("m = 1.0", "m = -1.0", ["m", "-1"]),
    ("k = 10.0", "k = 0.0", ["k"]),
    ('type = "linear"', 'type = "bilinear"', ["bilinear", "linear", "duffing"]),
    ('kernel = "matern32"', 'kernel = "rbf"', ["rbf", "matern32"]),
    ("dof = 0\nnoise_std = 0.05", "dof = 3\nnoise_std = 0.05", ["dof", "3"]),
    ('column = "acc"', 'column = "accel"', ["accel", "acc"]),
    ("noise_std = 0.05", "noise_std = 0.0", ["noise_std"]),
    ('method = "kalman"', 'method = "kalman"\nparticles = ', ["line"]),
    ('kernel = "matern32"', 'kernel = "matern23"', ["matern23", "did you mean 'matern32'"]),
    ('method = "kalman"', 'method = "kalman-mcmc"\niterations = "Auto"', ["iterations", "'Auto'", '"auto"']),
    ("noise_std = 0.05", 'noise_std = 0.05\nunit = "G"', ["'G'", "did you mean 'g'"]),
    # a sample rate that contradicts the file's time column (20 Hz): it would rescale every frequency
    ('time_column = "time"', "sample_rate = 100.0", ["sample_rate", "100", "0.05", "20 Hz", "data.csv"]),
]


@pytest.mark.parametrize("old,new,words", BAD_CONFIGS)
def test_bad_config_gives_one_clear_paragraph(workdir, old, new, words):
    name = _edit(workdir, old, new)
    code, out = invoke("estimate", name, "--out", "never")
    assert code != 0
    assert "Traceback" not in out and "error" in out.lower()
    for w in words:
        assert w in out, (w, out)
    assert not (workdir / "never").exists()


def test_nonlinear_system_with_kalman_is_refused(workdir):
    text = (
        (workdir / "lf.toml")
        .read_text()
        .replace('type = "linear"', 'type = "duffing"')
        .replace("k = 10.0", "k = 10.0\nk3 = 100.0")
    )
    (workdir / "duff.toml").write_text(text)
    code, out = invoke("estimate", "duff.toml", "--out", "never")
    assert code != 0 and "pgas" in out and "Traceback" not in out


@pytest.mark.parametrize("problem", ["missing", "nan", "uneven", "text", "empty"])
def test_bad_data_file(workdir, problem):
    data = (workdir / "data.csv").read_text().splitlines()
    if problem == "missing":
        os.remove(workdir / "data.csv")
    elif problem == "nan":
        cells = data[5].split(",")
        cells[1] = "nan"
        data[5] = ",".join(cells)
    elif problem == "uneven":
        cells = data[5].split(",")
        cells[0] = str(float(cells[0]) + 0.013)
        data[5] = ",".join(cells)
    elif problem == "text":
        cells = data[7].split(",")
        cells[1] = "abc"
        data[7] = ",".join(cells)
    elif problem == "empty":
        data = data[:1]
    if problem != "missing":
        (workdir / "data.csv").write_text("\n".join(data) + "\n")
    code, out = invoke("estimate", "lf.toml", "--out", "never")
    assert code != 0 and "Traceback" not in out and "data.csv" in out, out
    assert not (workdir / "never").exists()


def test_missing_skip_accepts_nan(workdir):
    data = (workdir / "data.csv").read_text().splitlines()
    cells = data[5].split(",")
    cells[1] = "nan"
    data[5] = ",".join(cells)
    (workdir / "data.csv").write_text("\n".join(data) + "\n")
    (workdir / "skip.toml").write_text(CONFIG.format(missing="skip"))
    code, out = invoke("estimate", "skip.toml", "--out", "res")
    assert code == 0, out


def test_missing_skip_refuses_a_channel_with_no_value(workdir):
    """missing = "skip" with a channel that is NaN throughout: an error naming it, not a run that
    returns the prior as if it had estimated something."""
    rows = (workdir / "data.csv").read_text().splitlines()
    out = [rows[0]]
    for row in rows[1:]:
        cells = row.split(",")
        cells[1] = "nan"
        out.append(",".join(cells))
    (workdir / "data.csv").write_text("\n".join(out) + "\n")
    (workdir / "skip.toml").write_text(CONFIG.format(missing="skip"))
    code, out = invoke("estimate", "skip.toml", "--out", "never")
    assert code != 0 and "Traceback" not in out and "'acc'" in out and "no finite value" in out, out
    assert not (workdir / "never").exists()


def test_data_override_and_unknown_demo(workdir):
    os.rename(workdir / "data.csv", workdir / "other.csv")
    assert invoke("estimate", "lf.toml", "--data", "other.csv", "--out", "res")[0] == 0
    code, out = invoke("demo", "nosuch")
    assert code != 0 and "oma" in out


# ----- every method end to end, and the convergence verdict ------------------------
def _inferred(method: str, extra: str = "") -> str:
    text = CONFIG.format(missing="error").replace(
        "variance = 2.0", 'variance = { prior = "lognormal", mu = 0.7, sigma = 1.0, init = 1.0 }'
    )
    if method == "pgas":  # the cubic stiffness inferred too
        k3 = 'k3 = { prior = "lognormal", mu = 1.6, sigma = 0.5, init = 4.0 }'
        text = text.replace('type = "linear"', 'type = "duffing"').replace("k = 10.0", f"k = 10.0\n{k3}")
        # a virtual sensor through the equation of motion, k3 included
        text = text.replace("[inference]", '[[outputs]]\nname = "inertia"\nacceleration = [1.0]\n\n[inference]')
        text = text.replace('method = "kalman"', 'method = "pgas"\nparticles = 16\nstate_every = 2')
    else:
        text = text.replace('method = "kalman"', f'method = "{method}"')
    return text + extra


@pytest.mark.parametrize("method", ["kalman-mcmc", "kalman-nuts", "pgas"])
def test_every_sampling_method_writes_a_result_folder_with_its_verdict(workdir, method, lowered_programs):
    """estimate through the CLI: summary keys and columns, figures, posterior.nc opened by
    ArviZ, and the convergence verdict (a short run: not converged, and its figures say so).
    And every compiled program of the run is free of LAPACK calls (``latentforce.linalg`` says
    why): chains vmapped, which is what batches the factorisations; for pgas k3 is sampled, so
    the per-chain model is in every program, and the filter's mode search starts the run."""
    import arviz as az

    from latentforce.inference import kalman_mcmc, kalman_nuts, laplace, mixture, particle_model, pgas

    lowered_programs.record(kalman_mcmc, kalman_nuts, laplace, mixture, pgas, particle_model)
    short = "iterations = 40\nburn_in = 20\nchains = 2\n"
    (workdir / "m.toml").write_text(_inferred(method, short))
    code, out = invoke("estimate", "m.toml", "--out", "res")
    assert code == 0, out
    expected = {
        "kalman-mcmc": {"_value_and_grad", "_run_chains", "_batch"},
        "kalman-nuts": {"_value_and_grad", "_init_chains", "_run_chains", "_batch"},
        "pgas": {"_value_and_grad", "_run_chunk", "_shapes", "_centres", "_smooth", "init_chains", "_derived_program"},
    }[method]
    assert expected <= lowered_programs.names, lowered_programs.names
    assert lowered_programs.lapack_calls() == []
    assert "NOT CONVERGED" in out  # 40 draws cannot reach an ESS of 400: said on stderr ...
    summary = json.loads((workdir / "res" / "summary.json").read_text())
    assert summary["method"] == method and summary["converged"] is False
    record = summary["convergence"]
    assert {"max_r_hat", "min_ess_bulk", "min_ess_tail", "worst", "target_ess"} <= set(record)
    assert record["worst"] and record["min_ess_bulk"] < 400
    assert {"mean", "sd", "r_hat", "ess_bulk"} <= set(summary["parameters"]["force_variance"])
    if method == "pgas":  # k3 is a parameter like the force's, and each draw's k3 makes its accelerations
        assert {"mean", "sd", "r_hat", "ess_bulk"} <= set(summary["parameters"]["k3"])
        assert "inertia_mean" in (workdir / "res" / "summary.csv").read_text().splitlines()[0]
    if method == "pgas":  # a path that neither the sweep nor the smoother move renewed is named as the cause
        from latentforce.estimate_particles import LOW_SMOOTHER_ACCEPTANCE, LOW_SWITCH_RATE

        assert summary["diagnostics"]["particles"] == 16  # the count the sweep ran with
        rates, accepted = summary["diagnostics"]["switch_rate"], summary["diagnostics"]["acceptance_smoother"]
        low = sum(rates) / len(rates) < LOW_SWITCH_RATE and sum(accepted) / len(accepted) < LOW_SMOOTHER_ACCEPTANCE
        assert ("hardly renewed the path" in " ".join(summary["diagnostics"]["warnings"])) == low
        # a displacement channel is measured here: no advice to add one
        assert "which no sensor measures" not in " ".join(summary["diagnostics"]["warnings"])
    header = (workdir / "res" / "summary.csv").read_text().splitlines()[0].split(",")
    assert header[:3] == ["time", "displacement_mean", "displacement_sd"] and "force_sd" in header
    figures = {p.name for p in (workdir / "res" / "figures").iterdir()}
    assert {"force.png", "traces.png", "histograms.png"} <= figures
    tree = az.from_netcdf(workdir / "res" / "posterior.nc")
    assert "force_variance" in tree.posterior and "force" in tree.posterior
    if method == "pgas":  # paths every state_every-th iteration: the full chains in their own group ...
        assert "pairs.png" in figures  # (k3 and the force variance)
        chains = tree.parameter_chains
        assert chains.sizes["draw"] > tree.posterior.sizes["draw"]
        acceptance = tree.sample_stats["acceptance"]  # the parameters' MH acceptance, per chain
        assert acceptance.dims == ("chain",) and np.allclose(acceptance.values, summary["acceptance"])
        # ... from which the file gives summary.json's numbers (the thinned draws do not)
        table = az.summary(tree, group="parameter_chains", var_names=["force_variance", "k3"], round_to="none")
        for name in ("force_variance", "k3"):
            assert np.isclose(table.loc[name, "mean"], summary["parameters"][name]["mean"], rtol=1e-9)
            assert np.isclose(table.loc[name, "r_hat"], summary["parameters"][name]["r_hat"], rtol=1e-6)
    # ... with --strict the exit code says so too, and the results are written all the same.
    code, out = invoke("estimate", "m.toml", "--out", "res", "--force", "--strict")
    assert code == 3 and (workdir / "res" / "summary.json").is_file(), out


def test_an_auto_warm_up_past_half_of_max_time_is_cut_and_the_run_says_so(workdir):
    """``max_time`` caps the warm-up too: still adapting at half of it, an "auto" run ends the warm-up at
    that chunk's end and samples (here 1 ms: the first of two warm-up chunks is past it), and its summary
    gives the warm-up run beside ``burn_in`` and a warning saying what to change."""
    (workdir / "m.toml").write_text(_inferred("kalman-mcmc", "burn_in = 200\nchains = 2\nmax_time = 0.001\n"))
    code, out = invoke("estimate", "m.toml", "--out", "res")
    assert code == 0, out
    summary = json.loads((workdir / "res" / "summary.json").read_text())
    d = summary["diagnostics"]
    assert d["burn_in"] == 200 and d["warmup"] == 100 and d["iterations"] == "auto" and d["draws_per_chain"] == 100
    assert summary["converged"] is False
    cut = [w for w in d["warnings"] if w.startswith("the warm-up stopped after 100 of its 200 iterations")]
    assert len(cut) == 1 and "max_time" in cut[0] and "burn_in" in cut[0], d["warnings"]


def test_exact_kalman_is_converged_and_strict_passes(workdir):
    code, out = invoke("estimate", "lf.toml", "--out", "res", "--strict")
    assert code == 0, out
    summary = json.loads((workdir / "res" / "summary.json").read_text())
    assert summary["converged"] is True and summary["convergence"] == {"exact": True}
    assert "warnings" not in summary["diagnostics"]
    # a key this method does not read is named on stderr and in the summary (and changes nothing else)
    text = (workdir / "lf.toml").read_text().replace("[inference]", "[inference]\nparticles = 100")
    (workdir / "pf.toml").write_text(text)
    code, out = invoke("estimate", "pf.toml", "--out", "res2", "--strict")
    assert code == 0 and "particles (pgas only)" in out, out
    again = json.loads((workdir / "res2" / "summary.json").read_text())
    assert any("particles (pgas only)" in w for w in again["diagnostics"]["warnings"])


def test_a_converged_run_has_no_stamp_and_an_unconverged_one_has(workdir):
    from matplotlib.figure import Figure

    from latentforce import plots
    from latentforce.results import read_results

    (workdir / "m.toml").write_text(_inferred("kalman-mcmc", "chains = 2\n"))
    code, out = invoke("estimate", "m.toml", "--out", "res", "--strict")  # "auto": runs to converged
    assert code == 0, out
    assert "NOT CONVERGED" not in out
    result = read_results(workdir / "res")
    assert result.convergence["converged"] and not plots.not_converged(result)
    for record, stamped in ((result.convergence, False), (dict(result.convergence, converged=False), True)):
        result.convergence = record
        fig = Figure()
        fig.add_subplot()
        plots.stamp_unconverged(fig, result)
        texts = [t.get_text() for t in fig.texts]
        assert any("NOT CONVERGED" in t for t in texts) == stamped, texts


@pytest.mark.slow
def test_pgas_auto_runs_until_converged_and_strict_passes(workdir):
    """pgas with iterations = "auto" (the default) on a Duffing record with a Matérn-3/2 force
    and its variance inferred, displacement and acceleration: the run stops by itself once
    converged (about 5 min), says how many iterations it took, and --strict exits 0."""
    (workdir / "m.toml").write_text(_inferred("pgas", "burn_in = 400\nmax_time = 500\n"))
    code, out = invoke("estimate", "m.toml", "--out", "res", "--strict")
    assert code == 0, out
    summary = json.loads((workdir / "res" / "summary.json").read_text())
    assert summary["converged"] is True, summary["convergence"]
    diag = summary["diagnostics"]
    assert diag["iterations_setting"] == "auto" and diag["stopped"] == "converged"
    assert 0 < diag["iterations"] < 50_000
    assert summary["convergence"]["max_r_hat"] <= 1.01


def test_pgas_auto_stops_at_max_time_and_says_so(workdir):
    """iterations = "auto" with a max_time too short to converge: the run stops after its first
    check, writes its results, says NOT CONVERGED and why it stopped; --strict exits 3."""
    text = _inferred("pgas", "burn_in = 100\nchains = 2\nmax_time = 1\n")
    (workdir / "m.toml").write_text(text.replace("particles = 16\n", ""))  # particles left to "auto"
    code, out = invoke("estimate", "m.toml", "--out", "res", "--strict")
    assert code == 3, out
    assert "NOT CONVERGED" in out
    summary = json.loads((workdir / "res" / "summary.json").read_text())
    assert summary["converged"] is False
    diag = summary["diagnostics"]
    assert diag["iterations_setting"] == "auto" and diag["stopped"] == "max_time"
    assert 0 < diag["iterations"] < 2_000
    assert diag["particles"] == 50  # "auto" on a short record (no window move): pgas_defaults.default_particles
    assert any("[t=" in w["name"] or w["name"] == "force_variance" for w in summary["convergence"]["worst"])


def test_simulate_starts_from_the_initial_table(workdir):
    """``simulate`` draws the start from ``[initial]`` (mechanical and force states), where a
    config has one; it used to ignore the table and start at rest with a stationary force."""
    import numpy as np
    import pandas as pd

    text = CONFIG.format(missing="error") + "\n[initial]\nmean = [0.5, -0.2, 3.0, 0.0]\nsd = [1e-6, 1e-6, 1e-6, 1e-6]\n"
    (workdir / "init.toml").write_text(text)
    code, out = invoke("simulate", "init.toml", "--out", "init.csv", "--duration", "1", "--sample-rate", "50")
    assert code == 0, out
    first = pd.read_csv(workdir / "init.csv").iloc[0]
    np.testing.assert_allclose([first["displacement"], first["velocity"], first["force"]], [0.5, -0.2, 3.0], atol=1e-4)
    # the default start is still rest
    first = pd.read_csv(workdir / "data.csv").iloc[0]
    assert first["displacement"] == 0.0 and first["velocity"] == 0.0


def test_help_names_the_config_keys():
    """--help names keys as [data].path: rich read the brackets as markup and printed ".path"."""
    code, out = invoke("estimate", "--help")
    assert code == 0 and "[data].path" in out and "[inference].seed" in out, out


def test_a_time_column_in_milliseconds_is_warned_about(workdir):
    """Time in ms makes the step 50 s against a 0.5 Hz structure: a finite, meaningless answer
    unless the run says that its natural frequency is above the data's Nyquist frequency."""
    import pandas as pd

    data = pd.read_csv(workdir / "data.csv")
    data["time"] = data["time"] * 1000.0
    data.to_csv(workdir / "data.csv", index=False)
    code, out = invoke("estimate", "lf.toml", "--out", "res")
    assert code == 0 and "Nyquist" in out and "0.5033 Hz" in out and "milliseconds" in out, out
    summary = json.loads((workdir / "res" / "summary.json").read_text())
    assert any("Nyquist" in w for w in summary["diagnostics"]["warnings"])


@pytest.mark.parametrize(
    "system",
    [
        "m = 1.0\nc = 0.0\nk = 10.0",
        # MDOF, C = 0: the undamped modes' real parts are -1e-15, which a test of >= 0 let through
        "M = [[2.0, 0.0], [0.0, 1.0]]\nC = [[0.0, 0.0], [0.0, 0.0]]\nK = [[3000.0, -1000.0], [-1000.0, 1000.0]]",
    ],
)
def test_an_undamped_structure_is_refused_with_the_reason(workdir, system):
    text = CONFIG.format(missing="error").replace("m = 1.0\nc = 0.4\nk = 10.0", system)
    (workdir / "undamped.toml").write_text(text)
    code, out = invoke("estimate", "undamped.toml", "--out", "never")
    assert code != 0 and "Traceback" not in out, out
    assert "not asymptotically stable" in out and "damping" in out and "[initial]" in out, out


def test_kalman_says_when_the_model_cannot_have_made_the_data(workdir):
    """Standardised one-step prediction errors (fit_check): mean square ~1 on data simulated from
    the config (within 4 sd of 1 over 201 samples), and a warning when the accelerations are in g
    but labelled m/s^2, which ran without a word before (force NMSE 117 % in the review)."""
    import math

    import pandas as pd

    code, out = invoke("estimate", "lf.toml", "--out", "res")
    assert code == 0 and "does not fit" not in out, out
    errors = json.loads((workdir / "res" / "summary.json").read_text())["diagnostics"]["prediction_errors"]
    assert set(errors) == {"acc", "disp"}
    for value in errors.values():
        assert abs(value - 1.0) < 4 * math.sqrt(2 / 201), errors
    data = pd.read_csv(workdir / "data.csv")
    data["acc"] = data["acc"] / 9.80665
    data.to_csv(workdir / "in_g.csv", index=False)
    code, out = invoke("estimate", "lf.toml", "--data", "in_g.csv", "--out", "bad")
    assert code == 0 and "does not fit" in out and "units" in out, out
