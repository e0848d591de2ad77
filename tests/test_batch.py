"""``latentforce batch``: many records on a real Dask LocalCluster, failures, reruns, refusals."""

import csv
import json
from datetime import datetime

import numpy as np
import pytest
from typer.testing import CliRunner

from latentforce.batch import (
    EXIT_SOME_FAILED,
    folder_names,
    name_timestamp,
    plan_records,
)
from latentforce.cli import app
from latentforce.errors import LatentForceError

runner = CliRunner()

CONFIG = """
[data]
time_column = "time"

[system]
type = "linear"
m = 1.0
c = 0.4
k = {k}

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
{inference}
"""
KALMAN = 'method = "kalman"'
STIFFNESS_PRIOR = '{ prior = "normal", mean = 10.0, sd = 4.0, init = 10.0 }'
MCMC = 'method = "kalman-mcmc"\niterations = 300\nburn_in = 200\nchains = 2'


def invoke(*args):
    result = runner.invoke(app, [str(a) for a in args])
    return result.exit_code, result.output + (result.stderr if result.stderr_bytes is not None else "")


def simulate(tmp, out, *, k=10.0, seed=0, duration=5.0):
    (tmp / "sim.toml").write_text(CONFIG.format(k=k, inference=KALMAN))
    code, text = invoke(
        "simulate",
        tmp / "sim.toml",
        "--out",
        out,
        "--duration",
        duration,
        "--sample-rate",
        20,
        "--seed",
        seed,
        "--force",
    )
    assert code == 0, text


def read_table(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def mtimes(folder):
    return {p: p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def cache_env(tmp_path_factory):
    """The compile cache the workers share (they inherit the environment when they start)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LATENTFORCE_CACHE_DIR", str(tmp_path_factory.mktemp("xla-cache")))
        yield


@pytest.fixture(scope="module")
def scheduler(cache_env):
    """A running two-worker cluster, reached by address as a remote one would be (--scheduler)."""
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        yield cluster.scheduler_address


# ----- names, order, inputs -------------------------------------------------------------------


def test_name_timestamp():
    assert name_timestamp("bridge_2026-11-26T01-00.csv") == datetime(2026, 11, 26, 1, 0)
    assert name_timestamp("acc-2026-11-26_01-02-03.h5") == datetime(2026, 11, 26, 1, 2, 3)
    assert name_timestamp("acc_20261126_0130.csv") == datetime(2026, 11, 26, 1, 30)
    assert name_timestamp("event_2026-11-26.mat") == datetime(2026, 11, 26)
    assert name_timestamp("run_20261126.csv") is None  # eight digits alone: an id, not a date
    assert name_timestamp("rec_2026-13-40T01-00.csv") is None  # no 13th month
    assert name_timestamp("record7.csv") is None


def test_folder_names_disambiguate(tmp_path):
    paths = [
        tmp_path / "a" / "rec.csv",
        tmp_path / "a" / "rec.h5",
        tmp_path / "b" / "rec.csv",
        tmp_path / "b" / "other.csv",
        tmp_path / "c" / "REC.nc",
    ]
    names = folder_names(paths)
    assert names == ["a--rec.csv", "rec.h5", "b--rec.csv", "other", "REC.nc"]
    assert len({n.casefold() for n in names}) == len(names)


def test_plan_records_order_and_inputs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "d").mkdir()
    for name in ("s_2026-11-26T02-00.csv", "s_2026-11-26T01-00.csv", "notes.txt"):
        (tmp_path / "d" / name).write_text("time,acc\n0,1\n")
    records, order = plan_records(["d/s_2026-11-26T02-00.csv", "d/*.csv"])
    assert order == "time" and [r.folder for r in records] == ["s_2026-11-26T01-00", "s_2026-11-26T02-00"]
    (tmp_path / "d" / "plain.csv").write_text("time,acc\n0,1\n")
    records, order = plan_records(["d/s_2026-11-26T02-00.csv", "d"])  # a folder: its data files
    assert order == "file"
    assert [r.folder for r in records] == ["s_2026-11-26T02-00", "plain", "s_2026-11-26T01-00"]
    with pytest.raises(LatentForceError, match="No file matches 'd/\\*.h5'"):
        plan_records(["d/*.h5"])
    with pytest.raises(LatentForceError, match="'d/missing.csv' does not exist"):
        plan_records(["d/missing.csv"])


# ----- a campaign end to end ------------------------------------------------------------------


def test_campaign_failures_rerun_and_changed_config(tmp_path, monkeypatch, scheduler):
    monkeypatch.chdir(tmp_path)
    rec = tmp_path / "rec"
    rec.mkdir()
    # given in file order 03, 01, 02 below: the table must come out in time order
    for hour, seed in ((1, 1), (2, 2), (3, 3)):
        simulate(tmp_path, rec / f"bridge_2026-11-26T0{hour}-00.csv", seed=seed)
    (rec / "bridge_2026-11-26T04-00.csv").write_text("time,acc\n0.0,1.0\n0.05,2.0\n")  # no disp column
    nan_rows = "".join(f"{0.05 * i},nan,nan\n" for i in range(20))
    (rec / "bridge_2026-11-26T05-00.csv").write_text("time,acc,disp\n" + nan_rows)  # NaN everywhere
    (tmp_path / "lf.toml").write_text(CONFIG.format(k=10.0, inference=KALMAN))

    code, text = invoke(
        "batch", "lf.toml", "rec/bridge_2026-11-26T03-00.csv", "rec/*.csv", "--out", "camp", "--scheduler", scheduler
    )
    assert code == EXIT_SOME_FAILED, text
    assert "error: rec/bridge_2026-11-26T04-00.csv" in text and "'disp' not found" in text
    assert "error: rec/bridge_2026-11-26T05-00.csv" in text
    rows = read_table(tmp_path / "camp" / "batch.csv")
    assert [r["folder"] for r in rows] == [f"bridge_2026-11-26T0{h}-00" for h in range(1, 6)]
    assert [r["status"] for r in rows] == ["done"] * 3 + ["failed"] * 2
    assert "'disp' not found" in rows[3]["error"] and "NaN" in rows[4]["error"]
    assert rows[0]["timestamp"] == "2026-11-26T01:00:00" and rows[0]["converged"] == "true"
    assert all(float(r["wall_time_s"]) > 0 for r in rows[:3])
    png = (tmp_path / "camp" / "trend.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000

    # each record's folder is what `estimate` writes for that file
    code, text = invoke("estimate", "lf.toml", "--data", "rec/bridge_2026-11-26T02-00.csv", "--out", "single")
    assert code == 0, text
    folder = tmp_path / "camp" / "bridge_2026-11-26T02-00"
    assert (folder / "summary.csv").read_text() == (tmp_path / "single" / "summary.csv").read_text()
    ours, theirs = (json.loads((d / "summary.json").read_text()) for d in (folder, tmp_path / "single"))
    assert ours["log_likelihood"] == theirs["log_likelihood"] and ours["nmse"] == theirs["nmse"]
    assert sorted(p.name for p in (folder / "figures").iterdir()) == sorted(
        p.name for p in (tmp_path / "single" / "figures").iterdir()
    )
    # force_rms: the root mean square of the posterior mean force, from summary.csv
    force_mean = np.loadtxt(folder / "summary.csv", delimiter=",", skiprows=1)[:, 5]
    assert float(rows[1]["force_rms"]) == pytest.approx(np.sqrt(np.mean(force_mean**2)), rel=1e-12)

    # rerun: finished records skipped and untouched; the broken ones retried (and fail again)
    before = {h: mtimes(tmp_path / "camp" / f"bridge_2026-11-26T0{h}-00") for h in (1, 2, 3)}
    code, text = invoke("batch", "lf.toml", "rec", "--out", "camp", "--scheduler", scheduler)
    assert code == EXIT_SOME_FAILED, text
    again = read_table(tmp_path / "camp" / "batch.csv")
    assert [r["status"] for r in again] == ["skipped"] * 3 + ["failed"] * 2
    assert [r["force_rms"] for r in again[:3]] == [r["force_rms"] for r in rows[:3]]
    assert {h: mtimes(tmp_path / "camp" / f"bridge_2026-11-26T0{h}-00") for h in (1, 2, 3)} == before

    # the campaign extended: the broken files gone, a new record added; only it runs
    for h in (4, 5):
        (rec / f"bridge_2026-11-26T0{h}-00.csv").unlink()
    simulate(tmp_path, rec / "bridge_2026-11-26T06-00.csv", seed=6)
    code, text = invoke("batch", "lf.toml", "rec/*.csv", "--out", "camp", "--scheduler", scheduler)
    assert code == 0, text
    assert [r["status"] for r in read_table(tmp_path / "camp" / "batch.csv")] == ["skipped"] * 3 + ["done"]

    # a changed config is refused, naming the folders, nothing rewritten; --force replaces
    (tmp_path / "lf.toml").write_text(CONFIG.format(k=12.0, inference=KALMAN))
    code, text = invoke("batch", "lf.toml", "rec/*.csv", "--out", "camp", "--scheduler", scheduler)
    assert code == 1 and "camp/bridge_2026-11-26T01-00" in text and "--force" in text
    assert "Traceback" not in text
    assert {h: mtimes(tmp_path / "camp" / f"bridge_2026-11-26T0{h}-00") for h in (1, 2, 3)} == before
    code, text = invoke(
        "batch", "lf.toml", "rec/bridge_2026-11-26T01-00.csv", "--out", "camp", "--scheduler", scheduler, "--force"
    )
    assert code == 0, text
    replaced = read_table(tmp_path / "camp" / "batch.csv")
    assert [(r["folder"], r["status"]) for r in replaced] == [("bridge_2026-11-26T01-00", "done")]
    record = json.loads((tmp_path / "camp" / "bridge_2026-11-26T01-00" / "batch_record.json").read_text())
    assert record["status"] == "done" and record["row"]["force_rms"] == float(replaced[0]["force_rms"])
    assert record["row"]["force_rms"] != float(rows[0]["force_rms"])  # k = 12 now: another force


def test_folder_not_written_by_batch_is_refused_then_forced(tmp_path, monkeypatch, cache_env):
    """A folder that batch did not write is refused; --force runs there, on the default LocalCluster."""
    monkeypatch.chdir(tmp_path)
    simulate(tmp_path, tmp_path / "r1.csv")
    (tmp_path / "lf.toml").write_text(CONFIG.format(k=10.0, inference=KALMAN))
    (tmp_path / "camp" / "r1").mkdir(parents=True)
    (tmp_path / "camp" / "r1" / "notes.txt").write_text("mine")
    code, text = invoke("batch", "lf.toml", "r1.csv", "--out", "camp")
    assert code == 1 and "camp/r1" in text and "batch_record.json" in text
    assert (tmp_path / "camp" / "r1" / "notes.txt").read_text() == "mine"
    assert not (tmp_path / "camp" / "batch.csv").exists()
    code, text = invoke("batch", "lf.toml", "r1.csv", "--out", "camp", "--workers", 1, "--force")
    assert code == 0, text
    assert [r["status"] for r in read_table(tmp_path / "camp" / "batch.csv")] == ["done"]
    assert (tmp_path / "camp" / "r1" / "notes.txt").read_text() == "mine"  # other files kept
    assert (tmp_path / "camp" / "r1" / "summary.json").is_file()


def test_unreachable_scheduler(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("latentforce.batch.CONNECT_TIMEOUT_S", 2.0)
    simulate(tmp_path, tmp_path / "r1.csv")
    (tmp_path / "lf.toml").write_text(CONFIG.format(k=10.0, inference=KALMAN))
    code, text = invoke("batch", "lf.toml", "r1.csv", "--out", "camp", "--scheduler", "tcp://127.0.0.1:1")
    assert code == 1 and "Cannot reach the Dask scheduler at 'tcp://127.0.0.1:1'" in text


@pytest.mark.slow  # two kalman-mcmc compiles at once: 4.6 min on the shared 2-core machine (load 10)
def test_stiffness_drop_shows_on_a_local_cluster(tmp_path, monkeypatch, cache_env):
    """kalman-mcmc on three records, the third of a structure that lost 40 % of its stiffness;
    the default LocalCluster (--workers 2)."""
    monkeypatch.chdir(tmp_path)
    truth = {1: 10.0, 2: 10.0, 3: 6.0}
    for hour, k in truth.items():
        simulate(tmp_path, tmp_path / f"deck_20261126_0{hour}00.csv", k=k, seed=hour, duration=10.0)
    (tmp_path / "mc.toml").write_text(CONFIG.format(k=STIFFNESS_PRIOR, inference=MCMC))
    code, text = invoke("batch", "mc.toml", "deck_*.csv", "--out", "camp", "--workers", 2)
    assert code == 0, text
    rows = read_table(tmp_path / "camp" / "batch.csv")
    assert [r["status"] for r in rows] == ["done"] * 3
    mean = np.array([float(r["k_mean"]) for r in rows])
    sd = np.array([float(r["k_sd"]) for r in rows])
    assert np.all(np.abs(mean - np.array(list(truth.values()))) < 4 * sd), (mean, sd)
    assert mean[1] - mean[2] > 2 * (sd[1] + sd[2]), (mean, sd)
    assert {"k_mean", "k_sd", "force_rms", "converged"} <= set(rows[0])
    print("wall time per record (s):", [round(float(r["wall_time_s"]), 1) for r in rows])


def test_unconverged_records_are_flagged_in_the_summary_line_the_trend_and_strict(tmp_path, monkeypatch):
    """A campaign whose finished records include unconverged runs says so: a warning naming them, the
    summary line's count, hollow red markers on trend.png (its title counts them) and --strict's exit
    code 3 (4 when a record failed). The rows stand in for run_batch's (the Dask runs are above)."""
    import matplotlib.image as mpimg

    import latentforce.batch as batch_module
    from latentforce.batch import BatchOutcome
    from latentforce.batch_report import not_converged, write_trend

    rows = [
        {"folder": "r1", "status": "done", "converged": True, "k_mean": 10.0, "k_sd": 0.1, "timestamp": ""},
        {"folder": "r2", "status": "done", "converged": False, "k_mean": 9.0, "k_sd": 0.1, "timestamp": ""},
        {"folder": "r3", "status": "skipped", "converged": "false", "k_mean": 8.0, "k_sd": 0.1, "timestamp": ""},
        {"folder": "r4", "status": "failed", "converged": "", "error": "x", "timestamp": ""},
    ]
    assert [r["folder"] for r in not_converged(rows)] == ["r2", "r3"]

    def red_pixels(folder, rows_):
        folder.mkdir(exist_ok=True)
        image = mpimg.imread(write_trend(folder, rows_, order="file"))
        return int(((image[..., 0] > 0.9) & (image[..., 1] < 0.1) & (image[..., 2] < 0.1)).sum())

    # hollow red rings on the unconverged records (the means are C0 blue; no failure drawn here)
    assert red_pixels(tmp_path / "flagged", rows[:3]) > 50
    assert red_pixels(tmp_path / "clean", [{**r, "converged": True} for r in rows[:3]]) == 0
    trend = tmp_path / "flagged" / "trend.png"
    (tmp_path / "lf.toml").write_text(CONFIG.format(k=10.0, inference=KALMAN))
    for failing, expected in ((False, 3), (True, EXIT_SOME_FAILED)):
        kept = rows if failing else rows[:3]
        outcome = BatchOutcome(rows=kept, order="file", table=tmp_path / "batch.csv", trend=trend)
        monkeypatch.setattr(batch_module, "run_batch", lambda *a, outcome=outcome, **k: outcome)
        code, text = invoke("batch", tmp_path / "lf.toml", tmp_path, "--out", tmp_path / "c", "--strict")
        assert code == expected, text
        assert "2 of the finished records did not converge (r2, r3)" in text and "(2 NOT CONVERGED)" in text
        code, text = invoke("batch", tmp_path / "lf.toml", tmp_path, "--out", tmp_path / "c")
        assert code == (EXIT_SOME_FAILED if failing else 0), text
