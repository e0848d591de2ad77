"""Checkpoint and resume: ``estimate`` killed with SIGKILL (after a checkpoint, during a checkpoint
write) and continued with ``--resume`` gives the uninterrupted run's draws, bit for bit.

The runs are real ``latentforce estimate`` processes on a small simulated record; the kill points
come from the test hook :data:`latentforce.checkpoint.TEST_STOP_ENV` (the writer stops after the
N-th write's temporary file is complete, or after its rename, and waits to be killed).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
import xarray as xr
from typer.testing import CliRunner

import latentforce
from latentforce import checkpoint as ckpt
from latentforce.cli import app
from latentforce.errors import LatentForceError

SRC = str(Path(latentforce.__file__).resolve().parents[1])

CONFIG = """
[data]
path = "data.csv"
time_column = "time"

[system]
type = "{system}"
m = 1.0
c = 0.4
k = 10.0
{k3}

[force]
kernel = "matern32"
variance = {{ prior = "lognormal", mu = 0.7, sigma = 1.0, init = 1.0 }}
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
checkpoint_every = 0
chains = 2
{inference}
"""

# kalman-mcmc runs until the verdict holds (chunks of 50 iterations): the stopping rule that
# reads the draws is exercised across the kills
KALMAN_MCMC = CONFIG.format(system="linear", k3="", inference='method = "kalman-mcmc"\nburn_in = 50\ntarget_ess = 100')
# a Duffing system: the path moves are re-shaped during the burn-in, so the blocks run in
# several segments (0-1, 1-3, 3-6, 6-end), each ending in a checkpoint
PGAS = CONFIG.format(
    system="duffing",
    k3="k3 = 5.0",
    inference='method = "pgas"\nparticles = 16\nstate_every = 2\niterations = 60\nburn_in = 20',
)

runner = CliRunner()


def invoke(*args):
    result = runner.invoke(app, [str(a) for a in args])
    return result.exit_code, result.output + (result.stderr if result.stderr_bytes is not None else "")


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A folder with the two configs and a 10 s record at 20 Hz (T = 201); the processes share
    one compilation cache."""
    work = tmp_path_factory.mktemp("resume")
    (work / "km.toml").write_text(KALMAN_MCMC)
    (work / "pg.toml").write_text(PGAS)
    old = os.getcwd()
    os.chdir(work)
    try:
        code, out = invoke("simulate", "km.toml", "--out", "data.csv", "--duration", "10", "--sample-rate", "20")
    finally:
        os.chdir(old)
    assert code == 0, out
    return work


def _env(work: Path, stop: str | None = None) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = SRC + os.pathsep + env.get("PYTHONPATH", "")
    env["LATENTFORCE_CACHE_DIR"] = str(work / "xla-cache")
    env.pop(ckpt.TEST_STOP_ENV, None)
    if stop is not None:
        env[ckpt.TEST_STOP_ENV] = stop
    return env


def estimate(work: Path, *args, stop: str | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "latentforce.cli", "estimate", *map(str, args)],
        cwd=work,
        env=_env(work, stop),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def finish(proc: subprocess.Popen) -> str:
    out, _ = proc.communicate(timeout=900)
    assert proc.returncode == 0, out
    return out


def kill_at(work: Path, folder: str, stop: str, *args) -> None:
    """Run ``estimate *args`` until its checkpoint writer reaches ``stop``, then SIGKILL it."""
    marker = work / folder / ckpt.TEST_STOPPED_NAME
    marker.unlink(missing_ok=True)
    proc = estimate(work, *args, stop=stop)
    deadline = time.monotonic() + 900
    while not marker.exists():
        if proc.poll() is not None:
            pytest.fail(f"the run ended before its checkpoint stop {stop}:\n{proc.communicate()[0]}")
        assert time.monotonic() < deadline, "the run never reached its checkpoint stop"
        time.sleep(0.2)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    marker.unlink()


def checkpoint_done(work: Path, folder: str) -> int:
    return ckpt.read_checkpoint(work / folder)[0]["done"]


def assert_identical(a: Path, b: Path) -> None:
    """The posterior and sample statistics in posterior.nc, and summary.csv, bit for bit."""
    ta, tb = xr.open_datatree(a / "posterior.nc"), xr.open_datatree(b / "posterior.nc")
    for group in ("posterior", "sample_stats"):
        da, db = ta[group].to_dataset(), tb[group].to_dataset()
        assert set(da.data_vars) == set(db.data_vars)
        for name in da.data_vars:
            assert np.array_equal(da[name].values, db[name].values), (group, name)
    assert (a / "summary.csv").read_bytes() == (b / "summary.csv").read_bytes()


def test_kalman_mcmc_killed_after_a_checkpoint_and_during_a_write_resumes_bit_identical(work, monkeypatch):
    """SIGKILL after the first checkpoint, then (resumed) during a checkpoint write; the
    resumed runs, stopped by the convergence verdict, give the uninterrupted run's draws."""
    finish(estimate(work, "km.toml", "--out", "ref-km"))  # first: the others use its compiled programs
    kill_at(work, "km", "1:renamed", "km.toml", "--out", "km")
    assert checkpoint_done(work, "km") == 50
    # a new run does not overwrite the interrupted one, and says how to continue it
    monkeypatch.chdir(work)
    code, out = invoke("estimate", "km.toml", "--out", "km")
    assert code == 1 and "--resume" in out and "Traceback" not in out
    # another config or other data is an error naming what differs; nothing is changed
    (work / "km-edit.toml").write_text(KALMAN_MCMC.replace("burn_in = 50", "burn_in = 60"))
    code, out = invoke("estimate", "km-edit.toml", "--resume", "km")
    assert code == 1 and "[inference].burn_in: 50 then, 60 now" in out, out
    lines = (work / "data.csv").read_text().splitlines()
    lines[3] = lines[3][:-1] + ("1" if lines[3][-1] != "1" else "2")
    (work / "other.csv").write_text("\n".join(lines) + "\n")
    code, out = invoke("estimate", "km.toml", "--resume", "km", "--data", "other.csv")
    assert code == 1 and "other.csv" in out and "differs" in out, out
    code, out = invoke("estimate", "km.toml", "--resume", "km", "--seed", "7")
    assert code == 1 and "seed" in out, out
    assert checkpoint_done(work, "km") == 50
    # resumed, then killed between writing its second checkpoint's temporary file and the rename
    kill_at(work, "km", "2:written", "km.toml", "--resume", "km")
    assert checkpoint_done(work, "km") == 100 and list(work.joinpath("km").glob(".checkpoint-*"))
    out = finish(estimate(work, "km.toml", "--resume", "km"))
    assert "(resumed)" in out
    assert_identical(work / "ref-km", work / "km")
    assert not (work / "km" / ckpt.CHECKPOINT_NAME).exists() and not list(work.joinpath("km").glob(".checkpoint-*"))
    summary = json.loads((work / "km" / "summary.json").read_text())
    assert summary["diagnostics"]["resumed"]["done"] == 100
    assert summary["diagnostics"]["draws_per_chain"] >= 100  # the verdict took more than one chunk
    # a finished folder: --resume says so
    code, out = invoke("estimate", "km.toml", "--resume", "km")
    assert code == 1 and "finished" in out, out


def test_resume_without_a_checkpoint_says_so(work, monkeypatch):
    monkeypatch.chdir(work)
    (work / "empty").mkdir(exist_ok=True)
    code, out = invoke("estimate", "km.toml", "--resume", "empty")
    assert code == 1 and "no checkpoint" in out and "Traceback" not in out, out
    code, out = invoke("estimate", "km.toml", "--resume", "nowhere")
    assert code == 1 and "no such result folder" in out, out


@pytest.mark.slow
def test_pgas_killed_during_a_checkpoint_write_resumes_bit_identical(work):
    """Three processes of pgas (about 1.5 min of processor time): slow."""
    finish(estimate(work, "pg.toml", "--out", "ref-pg"))
    kill_at(work, "pg", "2:written", "pg.toml", "--out", "pg")
    assert checkpoint_done(work, "pg") == 1  # the block segments: 0-1 saved, 1-3 not renamed
    finish(estimate(work, "pg.toml", "--resume", "pg"))
    assert_identical(work / "ref-pg", work / "pg")


@pytest.mark.slow
def test_pgas_killed_three_times_resumes_bit_identical(work):
    """After the first checkpoint, during a write, and in the middle (the last checkpoint
    before the final segment), each resumed from the one before."""
    if not (work / "ref-pg" / "summary.json").exists():
        finish(estimate(work, "pg.toml", "--out", "ref-pg"))
    kill_at(work, "pg3", "1:renamed", "pg.toml", "--out", "pg3")
    assert checkpoint_done(work, "pg3") == 1
    kill_at(work, "pg3", "1:written", "pg.toml", "--resume", "pg3")
    assert checkpoint_done(work, "pg3") == 1
    kill_at(work, "pg3", "2:renamed", "pg.toml", "--resume", "pg3")
    assert checkpoint_done(work, "pg3") == 6
    finish(estimate(work, "pg.toml", "--resume", "pg3"))
    assert_identical(work / "ref-pg", work / "pg3")


# ----- the checkpoint file on its own ------------------------------------------------------
def test_tree_round_trip_with_typed_keys_and_shape_check(tmp_path):
    tree = {"key": jax.random.split(jax.random.key(3), 2), "x": np.arange(6.0).reshape(2, 3), "n": np.int32(4)}
    arrays = ckpt.tree_arrays("s", tree)
    back = ckpt.tree_from_arrays(tree, arrays, "s")
    assert np.array_equal(jax.random.key_data(back["key"]), jax.random.key_data(tree["key"]))
    assert np.array_equal(back["x"], tree["x"]) and back["x"].dtype == np.float64
    arrays["s['x']"] = np.zeros((3, 2))
    with pytest.raises(LatentForceError, match="does not fit"):
        ckpt.tree_from_arrays(tree, arrays, "s")


def test_checkpoint_writes_at_most_every_so_often_and_reads_back(tmp_path):
    identity = {"seed": 0}
    state = ckpt.LoopState(7, False, {"a": np.arange(3.0)}, 1.5, {"stopped": None})
    slow = ckpt.Checkpoint(tmp_path, identity, every=3600.0)
    assert not slow.save("kalman-mcmc", lambda: state)  # not due: the builder is not even called
    assert not (tmp_path / ckpt.CHECKPOINT_NAME).exists()
    assert slow.save("kalman-mcmc", lambda: state, force=True)
    (tmp_path / ".checkpoint-abc.npz.tmp").write_bytes(b"half a write")
    meta, back = ckpt.read_checkpoint(tmp_path)
    assert meta["sampler"] == "kalman-mcmc" and meta["identity"] == identity
    assert (
        back.done == 7
        and not back.finished
        and back.elapsed_s == 1.5
        and np.array_equal(back.arrays["a"], np.arange(3.0))
    )
    resumed = ckpt.Checkpoint(tmp_path, identity, every=0.0, saved=back, sampler="kalman-mcmc")
    assert not list(tmp_path.glob(".checkpoint-*"))  # a killed write's leftovers are cleared
    with pytest.raises(LatentForceError, match="pgas"):
        resumed.restore("pgas")


def test_a_pgas_checkpoint_keeps_the_warm_ups_cut(tmp_path):
    """Where ``max_time`` cut an "auto" run's warm-up (``pgas.cut_warm_up``), the block it stopped at goes
    through the checkpoint file (a run restored from it numbers its later blocks as the first run did)."""
    from typing import NamedTuple

    from latentforce.inference.resume import pgas_loop_state, pgas_restore

    class Info(NamedTuple):
        accept: np.ndarray

    states = {"x": np.arange(4.0)}
    for cut in (None, 120):
        folder = tmp_path / str(cut)
        folder.mkdir()
        state = pgas_loop_state(states, [Info(np.ones((2, 3)))], np.zeros(2), 300, False, None, 9.0, cut)
        ckpt.Checkpoint(folder, {"seed": 0}, every=0.0).save("pgas", lambda: state, force=True)
        _, back = ckpt.read_checkpoint(folder)
        restored = pgas_restore(back, states, Info)
        assert restored[3:] == (300, False, None, cut)
        np.testing.assert_array_equal(restored[0]["x"], states["x"])


# ----- the samplers on their own: a checkpoint that "dies" at its N-th write -----------------
class _Killed(Exception):
    pass


class _DyingCheckpoint(ckpt.Checkpoint):
    """Writes every chunk and raises (as a kill would stop the run) right after write ``n``."""

    def __init__(self, folder, n):
        super().__init__(folder, {"seed": 0}, every=0.0)
        self.n = n

    def save(self, sampler, build, *, force=False):
        wrote = super().save(sampler, build, force=force)
        if self.writes == self.n:
            raise _Killed
        return wrote


@pytest.mark.slow
@pytest.mark.parametrize("method", ["kalman-mcmc", "kalman-nuts"])
def test_kalman_samplers_restored_in_process_draw_the_same(tmp_path, method):
    """Sampler level, both Kalman samplers (``kalman-nuts`` has no CLI test here): stopped after
    its second checkpoint, restored from the file, the draws and statistics equal the
    uninterrupted run's."""
    from latentforce.inference.kalman_mcmc import run_kalman_mcmc
    from latentforce.inference.kalman_nuts import run_kalman_nuts
    from latentforce.io.config import config_from_dict

    problem = config_from_dict(
        {
            "system": {"type": "linear", "m": 1.0, "c": 0.4, "k": 10.0},
            "force": {
                "kernel": "matern32",
                "variance": {"prior": "lognormal", "mu": 0.7, "sigma": 1.0, "init": 1.0},
                "lengthscale": 0.5,
            },
            "sensors": [{"column": "acc", "quantity": "acceleration", "dof": 0, "noise_std": 0.05}],
            "inference": {"method": method},
        }
    )
    rng = np.random.default_rng(0)
    y = np.cumsum(rng.standard_normal((150, 1)), axis=0) * 0.05
    mask = np.ones(y.shape, bool)
    free = {n: (s.prior, s.init) for n, s in problem.free.items()}
    sampler = run_kalman_mcmc if method == "kalman-mcmc" else run_kalman_nuts

    def run(checkpoint=None):
        return sampler(
            jax.random.key(5),
            problem.model,
            dict(problem.fixed),
            free,
            y,
            mask,
            0.05,
            iterations=40,
            burn_in=20,
            chains=2,
            chunk=10,
            checkpoint=checkpoint,
        )

    reference = run()
    with pytest.raises(_Killed):
        run(_DyingCheckpoint(tmp_path, 3))
    meta, saved = ckpt.read_checkpoint(tmp_path)
    assert meta["sampler"] == method and saved.done == 30 and not saved.finished
    resumed = run(ckpt.Checkpoint(tmp_path, {"seed": 0}, every=3600.0, saved=saved, sampler=method))
    for name in reference.draws:
        assert np.array_equal(reference.draws[name], resumed.draws[name])
    assert np.array_equal(reference.log_likelihood, resumed.log_likelihood)
    assert np.array_equal(reference.accepted, resumed.accepted)
