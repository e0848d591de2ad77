r"""Calibration of the nonlinear methods on Duffing and Bouc-Wen records: are the bands honest, and how fast?

For each case a Duffing record is simulated from the continuous model (RK4
substeps, a GP force of the case's Matérn order), measured with the case's
sensors and noise, and run through each method as a user runs it
(``latentforce.estimate.run`` on a config dict, defaults otherwise). Reported
per (case, method):

* coverage: the fraction of time samples whose true force (and displacement)
  lies inside the posterior mean ± 1, 2, 3 sd (nominal for a Gaussian
  posterior: 68.3 / 95.4 / 99.7 %, and the aims of the nonlinear-posterior
  issue: ±3 sd ≥ 95 %, ±1 sd 55-85 %);
* force NMSE (%) of the posterior mean;
* the run's own verdict: converged, max R-hat, min bulk ESS (the samplers;
  ``ekf``/``ukf`` at fixed parameters are deterministic);
* ``pgas``'s ancestor switch rate and its smoother move's acceptance; wall seconds to the result, compilation
  included.

The force hyperparameters are fixed at the truth in every case (the
trajectory question alone; parameter calibration is
``benchmarks/calibration.py``). The grid (full mode) spans the nonlinear share
of the restoring force (rms of k3 z^3 over rms of k z + k3 z^3, reported as
achieved), the four Matérn orders, sensor sets, noise levels, and records
starting at rest or cut from a run already in motion.

Usage::

    python benchmarks/nonlinear_calibration.py --quick   # one small case, every method (CI)
    python benchmarks/nonlinear_calibration.py           # the grid (hours on 2 cores)
    python benchmarks/nonlinear_calibration.py --methods ekf,ukf --orders 1,2
    python benchmarks/nonlinear_calibration.py --quick --orders 0,1,2,3   # the small case at every order
    python benchmarks/nonlinear_calibration.py --quick --orders 0,1,2,3 --sensors acc   # ... acceleration only
    python benchmarks/nonlinear_calibration.py --quick --orders 0,1,2,3 --sensors acc --k3 4e4   # ... milder
    python benchmarks/nonlinear_calibration.py --quick --orders 2 --sensors acc,vel --start moving --wide-initial
    python benchmarks/nonlinear_calibration.py --quick --system bouc-wen --orders 0,1   # the benchmark oscillator
    python benchmarks/nonlinear_calibration.py --quick --system bouc-wen --orders 2 --start virgin   # r0 known
    python benchmarks/nonlinear_calibration.py --quick --system frame --orders 0,1   # 3-storey frame, brace
    python benchmarks/nonlinear_calibration.py --quick --system bouc-wen-smooth --orders 0,1,2,3 --start virgin
    python benchmarks/nonlinear_calibration.py --quick --orders 0+2   # a kernel sum: slow Matérn-1/2 + fast 5/2

``--system bouc-wen``: the Bouc-Wen oscillator of the Noël & Schoukens benchmark
(``latentforce demo bouc-wen``'s system and force scale, 750 Hz, 450 samples, acceleration and
displacement); the hysteretic force's coverage is reported beside the force's and the
displacement's, and the nonlinear share is rms(r - alpha z) / rms(k z + r).

``--system bouc-wen-smooth``: a Bouc-Wen oscillator whose loop saturates fast (nu = 2), stiff at 500 Hz
(500 samples, velocity and displacement; ``latentforce/substeps.py``).
``--system frame``: ``latentforce demo frame``'s 3-storey shear frame with a Bouc-Wen brace
between floors 0 and 1 (100 Hz, 400 samples, accelerometers on floors 0 and 2; ``--sensors``
names channels as quantity and floor, ``acc0,acc2,disp1``); coverage pools every floor's
displacement, and the nonlinear share is rms(r - alpha d) / rms(k d + r) of the brace's storey
(d its drift).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

RESULTS_DIR = Path(__file__).resolve().parent / "results"
DT = 1.0 / 100.0
SYSTEM = dict(m=1.0, c=2.0, k=400.0)  # f_n = 3.2 Hz, 8 % damping
FORCE_VARIANCE = 100.0
#: the Bouc-Wen benchmark (Noël & Schoukens 2016) at its sample rate, with demo bouc-wen's force scale
BW_SYSTEM = dict(m=2.0, c=10.0, k=5.0e4, alpha=5.0e4, beta=800.0, gamma=-1100.0, nu=1.0)
BW_DT, BW_VARIANCE = 1.0 / 750.0, 2500.0
#: a smooth, fast-saturating loop (nu = 2; r bounded by (alpha / (beta + gamma))^(1/2) = 5.3 N) at 500 Hz:
#: its rate is stiff there, 18 RK4 substeps a sample by the rule of ``latentforce/substeps.py`` (4 before)
BWS_SYSTEM = dict(m=2.0, c=10.0, k=5.0e4, alpha=5.0e4, beta=1000.0, gamma=800.0, nu=2.0)
BWS_DT = 1.0 / 500.0
#: the Vibration 2020 paper's Duffing (Section 3) at its 2048 Hz, with a GP force of the whitened-NUTS
#: probe's scale: the issue on nonlinear posteriors' own first case (Matérn-3/2, acceleration only)
PAPER_SYSTEM = dict(m=1.0, c=20.0, k=1.0e4)
PAPER_DT, PAPER_VARIANCE, PAPER_K3 = 1.0 / 2048.0, 100.0, 1.0e9
NOMINAL = {1: 68.27, 2: 95.45, 3: 99.73}


def _orders(order) -> list[int]:
    return [int(o) for o in str(order).split("+")]


def kernel_label(order) -> str:
    """``Matérn-3/2``, or ``Matérn-1/2 + Matérn-5/2`` for a sum (``order = "0+2"``)."""
    return " + ".join(f"Matérn-{2 * o + 1}/2" for o in _orders(order))


def force_table(order, variance: float, lengthscale: float) -> dict:
    """``[force]`` of a case: one Matérn; or, for a sum (``order = "0+2"``), the variance split evenly
    and each term ten times slower than the next, the last at the case's lengthscale."""
    orders = _orders(order)
    kernel = " + ".join(f"matern{2 * o + 1}2" for o in orders)
    n = len(orders)
    if n == 1:
        return {"kernel": kernel, "variance": variance, "lengthscale": lengthscale}
    return {
        "kernel": kernel,
        "variance": [variance / n] * n,
        "lengthscale": [lengthscale * 10.0 ** (n - 1 - i) for i in range(n)],
    }


class Case(NamedTuple):
    order: int | str  # Matérn nu = order + 1/2; "0+2": a sum of Matérn-1/2 and 5/2 terms (force_table)
    k3: float
    sensors: str  # "acc", "acc,vel", "disp"
    noise: float  # noise sd as a fraction of each channel's rms
    start: str  # "rest", "moving", or "virgin" (from rest, the config saying so: ``virgin_initial``)
    T: int
    lengthscale: float = 0.05
    system: str = "duffing"

    @property
    def duffing(self) -> dict:
        """The Duffing's m, c, k (k3 is the case's own): the paper's at ``system = "paper"``."""
        return PAPER_SYSTEM if self.system == "paper" else SYSTEM

    @property
    def dt(self) -> float:
        return {"bouc-wen": BW_DT, "bouc-wen-smooth": BWS_DT, "paper": PAPER_DT}.get(self.system, DT)

    @property
    def label(self) -> str:
        if self.system == "frame":
            return (
                f"Frame, {kernel_label(self.order)}, {self.sensors}, {100 * self.noise:g} % noise, "
                f"{self.start}, T={self.T}"
            )
        if self.system in ("bouc-wen", "bouc-wen-smooth"):
            return (
                f"Bouc-Wen{' nu=2' if self.system == 'bouc-wen-smooth' else ''}, "
                f"{kernel_label(self.order)}, {self.sensors}, {100 * self.noise:g} % noise, "
                f"{self.start}, T={self.T}"
            )
        return ("Paper's Duffing (2048 Hz), " if self.system == "paper" else "") + (
            f"{kernel_label(self.order)}, k3={self.k3:g}, {self.sensors}, {100 * self.noise:g} % noise, "
            f"{self.start}, T={self.T}"
        )


QUICK = [Case(order=1, k3=4e5, sensors="acc,disp", noise=0.01, start="rest", T=256)]
QUICK_BOUC_WEN = [
    Case(order=0, k3=0.0, sensors="acc,disp", noise=0.01, start="rest", T=450, lengthscale=0.01, system="bouc-wen")
]
QUICK_BOUC_WEN_SMOOTH = [
    Case(
        order=2, k3=0.0, sensors="vel,disp", noise=0.01, start="rest", T=500, lengthscale=0.02, system="bouc-wen-smooth"
    )
]
QUICK_FRAME = [Case(order=0, k3=0.0, sensors="acc0,acc2", noise=0.01, start="rest", T=400, system="frame")]
QUICK_PAPER = [
    Case(order=1, k3=PAPER_K3, sensors="acc", noise=0.01, start="rest", T=1024, lengthscale=0.02, system="paper")
]
QUICK_CASES = {
    "duffing": QUICK,
    "bouc-wen": QUICK_BOUC_WEN,
    "bouc-wen-smooth": QUICK_BOUC_WEN_SMOOTH,
    "frame": QUICK_FRAME,
    "paper": QUICK_PAPER,
}


def grid() -> list[Case]:
    out = []
    for order, k3, sensors in itertools.product((0, 1, 2, 3), (4e4, 4e5, 4e6), ("acc", "acc,vel", "disp")):
        out.append(Case(order, k3, sensors, 0.01, "rest", 1024))
    for order in (0, 1):
        out.append(Case(order, 4e5, "acc", 0.05, "rest", 1024))
        out.append(Case(order, 4e5, "acc", 0.005, "rest", 1024))
        out.append(Case(order, 4e5, "acc", 0.01, "moving", 1024))
        out.append(Case(order, 4e5, "acc", 0.01, "rest", 4096))
    return out


QUANTITY = {"acc": "acceleration", "vel": "velocity", "disp": "displacement"}


def _sensor(token: str) -> dict:
    """``"acc"`` (DOF 0) or ``"acc2"`` (floor 2) as a ``[[sensors]]`` table."""
    kind, dof = token.rstrip("0123456789"), token[len(token.rstrip("0123456789")) :]
    return {"column": token, "quantity": QUANTITY[kind], "dof": int(dof or 0), "noise_std": 1.0}


def case_config(case: Case, method: str, max_time: float) -> dict:
    sensors = [_sensor(s) for s in case.sensors.split(",")]
    inference = {"method": method}
    if method == "pgas":
        inference["max_time"] = float(max_time)
    if case.system == "frame":
        from latentforce.demos import frame

        return {
            "data": {"sample_rate": frame.FS},
            "system": frame.SYSTEM,
            "force": force_table(case.order, frame.TRUE_VARIANCE, frame.TRUE_LENGTHSCALE),
            "sensors": sensors,
            "inference": inference,
        }
    bw, paper = case.system in ("bouc-wen", "bouc-wen-smooth"), case.system == "paper"
    system = {"type": "duffing", **case.duffing, "k3": case.k3}
    return {
        "data": {"sample_rate": 1.0 / case.dt},
        "system": {"type": "bouc-wen", **(BWS_SYSTEM if case.system == "bouc-wen-smooth" else BW_SYSTEM)}
        if bw
        else system,
        "force": force_table(
            case.order, BW_VARIANCE if bw else (PAPER_VARIANCE if paper else FORCE_VARIANCE), case.lengthscale
        ),
        "sensors": sensors,
        "inference": inference,
    }


def simulate(case: Case, seed: int):
    """``(y, truth, noise_sd, share)``: the record, its true displacement and force, the noise sds used."""
    import jax

    from latentforce.io.config import config_from_dict
    from latentforce.simulate import clean_signal
    from latentforce.simulate import simulate as run_sim
    from latentforce.substeps import needed as needed_substeps

    problem = config_from_dict(case_config(case, "pgas", 1.0))
    model = problem.model
    lead = 500 if case.start == "moving" else 0
    # 16 RK4 steps a sample, or as many as the system's rate needs (latentforce.substeps)
    fine = max(16, needed_substeps(model, dict(problem.fixed), case.dt))
    sim = run_sim(jax.random.key(seed), model, dict(problem.fixed), case.T + lead, case.dt, substeps=fine)
    z = sim.displacement[lead:, 0]
    clean = np.stack([clean_signal(sim, s)[lead:] for s in model.sensors], axis=1)
    noise_sd = case.noise * clean.std(axis=0)
    rng = np.random.default_rng(seed + 1)
    y = clean + rng.standard_normal(clean.shape) * noise_sd
    truth = {"displacement": z, "force": sim.force[lead:, 0]}
    if case.system == "frame":
        from latentforce.demos import frame

        brace = frame.BRACE
        drift = sim.displacement[lead:, brace["dofs"][0]] - sim.displacement[lead:, brace["dofs"][1]]
        r = sim.hysteretic_force[lead:, 0]
        truth = {"displacement": sim.displacement[lead:], "hysteretic_force": r, "force": sim.force[lead:, 0]}
        k = frame.SYSTEM["stiffnesses"][max(brace["dofs"])]
        share = float(np.std(r - brace["alpha"] * drift) / np.std(k * drift + r))
        return y, truth, noise_sd, share
    if case.system in ("bouc-wen", "bouc-wen-smooth"):
        r = sim.hysteretic_force[lead:, 0]
        truth["hysteretic_force"] = r
        share = float(np.std(r - BW_SYSTEM["alpha"] * z) / np.std(BW_SYSTEM["k"] * z + r))
        return y, truth, noise_sd, share
    cubic, linear = case.k3 * z**3, case.duffing["k"] * z
    share = float(np.std(cubic) / np.std(linear + cubic))
    return y, truth, noise_sd, share


def virgin_initial(problem) -> dict:
    """``[initial]`` for a record that starts from rest in a virgin state, as a user who knows it would
    write it: the default near-rest start (``LatentForceModel.default_initial``) with the hysteretic
    states' sd cut to a tenth (on the Bouc-Wen benchmark 14.1 -> 1.4 N, about 1 % of its peak hysteretic
    force) and their correlations scaled with it. The same as the default on a system without them."""
    model = problem.model
    mean, P = (np.array(a, dtype=float) for a in model.default_initial(dict(problem.fixed)))
    idx = np.arange(model.n_state)[model.layout.internal]
    P[idx, :] *= 0.1
    P[:, idx] *= 0.1
    return {"mean": mean.tolist(), "cov": P.tolist()}


def estimate_case(
    case: Case,
    method: str,
    seed: int,
    max_time: float,
    *,
    window=None,
    profile_steps=None,
    wide_initial=False,
    cache=None,
    inference=None,
):
    """``(result, truth, share)``: the case's record simulated at ``seed`` and run through ``estimate.run`` as a
    user runs it. ``window``: the window move's width forced (a probe; 0: off; None: its rule);
    ``profile_steps``: the profile move's steps a block forced (a probe; None: its default); ``wide_initial``:
    the linearised system's joint stationary prior as ``[initial]``; ``cache``: a persistent compilation cache
    directory; ``inference``: more ``[inference]`` keys (fixed counts: ``iterations``, ``burn_in``)."""
    import latentforce

    latentforce.enable_x64()
    from latentforce import estimate
    from latentforce.compile import persistent_cache
    from latentforce.io.config import config_from_dict
    from latentforce.io.data import Dataset

    if window is not None:
        import latentforce.inference.pgas as pg

        pg.default_window = lambda *args, width=int(window): width
    if profile_steps is not None:
        import latentforce.inference.profile_move as pmv

        pmv.PROFILE_STEPS = int(profile_steps)
    y, truth, noise_sd, share = simulate(case, seed)
    cfg = case_config(case, method, max_time)
    cfg["inference"].update(inference or {})
    for sensor, sd in zip(cfg["sensors"], noise_sd):
        sensor["noise_std"] = float(sd)
    problem = config_from_dict(cfg, source=f"<{case.label} {method}>")
    if wide_initial:  # the linearised system's joint stationary prior instead of the near-rest default
        _, P = problem.model.stationary_initial(dict(problem.fixed), linear_part=True)
        cfg["initial"] = {"mean": [0.0] * P.shape[0], "cov": np.asarray(P).tolist()}
        problem = config_from_dict(cfg, source=f"<{case.label} {method}>")
    elif case.start == "virgin":
        cfg["initial"] = virgin_initial(problem)
        problem = config_from_dict(cfg, source=f"<{case.label} {method}>")
    dataset = Dataset.from_array(y, case.dt, problem.columns)
    with persistent_cache(cache) if cache else contextlib.nullcontext():
        result, _ = estimate.run(problem, dataset, seed=seed)
    return result, truth, share


def worker(job_path: str, out_path: str) -> None:
    job = json.loads(Path(job_path).read_text())
    case = Case(**job["case"])
    result, truth, share = estimate_case(
        case,
        job["method"],
        job["seed"],
        job["max_time"],
        window=job.get("window"),
        profile_steps=job.get("profile_steps"),
        wide_initial=bool(job.get("wide_initial")),
        cache=job["cache"],
    )
    T = len(result.time)
    out = {"share": share, "wall_s": float(result.wall_time_s)}
    for state in truth:  # every column of the state (a frame's floors) pooled
        x = np.reshape(truth[state], (T, -1))
        width = x.shape[1]
        mean, sd = result.state_mean[state][:, :width], result.state_sd[state][:, :width]
        err = np.abs(x - mean)
        out[f"{state}_coverage"] = {k: float(100 * np.mean(err <= k * sd)) for k in (1, 2, 3)}
        out[f"{state}_nmse"] = float(100 * np.mean(np.mean((x - mean) ** 2, axis=0) / np.var(x, axis=0)))
    conv = dict(result.convergence or {})
    out.update(
        converged=bool(conv.get("converged", False)), max_r_hat=conv.get("max_r_hat"), min_ess=conv.get("min_ess_bulk")
    )
    sr = result.sample_stats.get("switch_rate")
    out["switch_rate"] = float(np.mean(sr)) if sr is not None and np.size(sr) else None
    acc = (result.diagnostics or {}).get("acceptance_smoother")
    out["smoother_acceptance"] = float(np.mean(acc)) if acc else None
    Path(out_path).write_text(json.dumps(out))


def run_job(case: Case, method: str, args, tmp: Path) -> dict:
    job, out = tmp / f"job-{abs(hash((case, method)))}.json", tmp / f"out-{abs(hash((case, method)))}.json"
    job.write_text(
        json.dumps(
            {
                "case": case._asdict(),
                "method": method,
                "seed": args.seed,
                "max_time": args.max_time,
                "cache": str(tmp / "cache"),
                "wide_initial": bool(args.wide_initial),
                "window": args.window,
                "profile_steps": args.profile_steps,
            }
        )
    )
    env = dict(os.environ)
    src = str(Path(__file__).resolve().parent.parent / "src")
    env["PYTHONPATH"] = src + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), "--worker", str(job), str(out)],
            capture_output=True,
            text=True,
            timeout=args.max_time + 900,
            env=env,
        )
    except subprocess.TimeoutExpired:
        return {"error": "timed out"}
    if proc.returncode != 0 or not out.exists():
        tail = (proc.stderr or proc.stdout or "").strip().splitlines()
        return {"error": f"exit {proc.returncode}: {tail[-1][:200] if tail else ''}"}
    res = json.loads(out.read_text())
    res["process_s"] = time.perf_counter() - t0
    return res


def fmt(x, digits=3) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return f"{x:.{digits}g}"


def cov_cell(c: dict) -> str:
    cells = []
    for k in (1, 2, 3):
        v = c[str(k)] if str(k) in c else c[k]
        bad = (k == 3 and v < 95.0) or (k == 1 and not 55.0 <= v <= 85.0)
        cells.append(f"**{v:.1f}**" if bad else f"{v:.1f}")
    return " / ".join(cells)


SYSTEM_NAMES = {"bouc-wen": "Bouc-Wen", "bouc-wen-smooth": "Bouc-Wen (nu = 2)", "frame": "MDOF frame"}


def report(rows: list[tuple[Case, str, dict]], args, total_s: float) -> str:
    load = os.getloadavg()
    lines = [
        f"# Calibration of the nonlinear methods on "
        f"{SYSTEM_NAMES.get(args.system, 'Duffing')} "
        f"records ({'quick' if args.quick else 'full'})",
        "",
        f"{time.strftime('%Y-%m-%dT%H:%M:%S')}; {platform.machine()}, {os.cpu_count()} cores, load average "
        f"{load[0]:.2f} at the end; seed {args.seed}; pgas max_time {args.max_time:g} s. "
        + {
            "bouc-wen": "Bouc-Wen benchmark oscillator (m = 2, c = 10, k = 5e4, alpha = 5e4, beta = 800, "
            f"gamma = -1100, nu = 1) at 750 Hz, force variance {BW_VARIANCE:g}",
            "bouc-wen-smooth": "Bouc-Wen oscillator with a smooth, fast-saturating loop (m = 2, c = 10, k = 5e4, "
            "alpha = 5e4, beta = 1000, gamma = 800, nu = 2; r within 5.3 N) at 500 Hz, force variance "
            f"{BW_VARIANCE:g}; RK4 substeps chosen by the rule (18)",
            "frame": "demo frame's 3-storey shear frame (5 kg, 1e4 N/m, 10 N s/m per storey; Bouc-Wen brace "
            "between floors 0 and 1: alpha = 1e4, beta = 60, gamma = 20, nu = 1) at 100 Hz, force at the top, "
            "variance 2500; displacement coverage pools the three floors",
            "paper": "the Vibration 2020 paper's Duffing (m = 1, c = 20, k = 1e4, 71 Hz, 10 % damping) at 2048 Hz, "
            f"force variance {PAPER_VARIANCE:g}, lengthscale 0.02 s",
        }.get(args.system, f"Duffing m = 1, c = 2, k = 400 (3.2 Hz, 8 % damping), force variance {FORCE_VARIANCE:g}")
        + ", hyperparameters fixed at the truth; noise sd as a fraction of each channel's rms; initial state: "
        + (
            "the linearised system's stationary covariance (`--wide-initial`)."
            if args.wide_initial
            else "the default (near rest)"
            + (
                "; `virgin` cases: `[initial]` says the record starts from rest in a virgin state (the "
                "default with the hysteretic force's sd cut to a tenth)."
                if any(case.start == "virgin" for case, _, _ in rows)
                else "."
            )
        )
        + ("" if args.window is None else f" Window move forced to width {args.window} (`--window`).")
        + ("" if args.profile_steps is None else f" Profile move: {args.profile_steps} steps a block."),
        "",
        "| case | nonlinear share | method | force ±1/±2/±3 sd % | displacement ±1/±2/±3 sd % "
        "| hysteretic force ±1/±2/±3 sd % | force NMSE % "
        "| converged | max R-hat | min bulk ESS | switch rate | smoother move acceptance | s |",
        "|---|---:|---|---|---|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for case, method, res in rows:
        if "error" in res:
            lines.append(f"| {case.label} | – | {method} | {res['error']} | | | | | | | | | |")
            continue
        lines.append(
            f"| {case.label} | {100 * res['share']:.0f} % | {method} | {cov_cell(res['force_coverage'])} | "
            f"{cov_cell(res['displacement_coverage'])} | "
            f"{cov_cell(res['hysteretic_force_coverage']) if 'hysteretic_force_coverage' in res else '–'} | "
            f"{fmt(res['force_nmse'])} | "
            f"{'yes' if res['converged'] else '**no**'} | {fmt(res['max_r_hat'], 4)} | {fmt(res['min_ess'])} | "
            f"{fmt(res['switch_rate'], 2)} | {fmt(res.get('smoother_acceptance'), 2)} | {res['wall_s']:.0f} |"
        )
    lines += [
        "",
        "Coverage in **bold** misses the aims (±3 sd ≥ 95 %, ±1 sd 55-85 %; nominal 68.3 / 95.4 / "
        "99.7 %). `ekf`/`ukf` at fixed parameters are deterministic (converged by definition); their "
        "coverage shows where a Gaussian answer is too sure. Coverage is over the time samples of one "
        "record: neighbouring samples are correlated, so it is a noisy measure; the calibration issue's "
        "SBC is the exact check.",
        "",
        f"Total benchmark time {total_s:.0f} s.",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one small case (minutes)")
    parser.add_argument("--methods", default="pgas,ekf,ukf")
    parser.add_argument(
        "--orders", default=None, help="only these Matérn orders (0..3), comma-separated; 0+2: a kernel sum (quick)"
    )
    parser.add_argument(
        "--sensors", default=None, help='quick mode: the small case with these sensors instead ("acc", "acc,vel", ...)'
    )
    parser.add_argument(
        "--start",
        default=None,
        help='quick mode: "rest", "moving" (a record cut from motion) or "virgin" (from rest in a virgin state, '
        "the config's [initial] saying so: the hysteretic force's default sd cut to a tenth)",
    )
    parser.add_argument(
        "--wide-initial",
        action="store_true",
        help="give every run the linearised system's stationary covariance as [initial] (not the near-rest default)",
    )
    parser.add_argument("--k3", type=float, default=None, help="quick mode: the Duffing k3 (nonlinear share)")
    parser.add_argument("--noise", type=float, default=None, help="quick mode: noise sd / channel rms")
    parser.add_argument("--samples", type=int, default=None, help="quick mode: record length T")
    parser.add_argument("--max-time", type=float, default=None, help="pgas max_time (default 180; quick 60)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--window", type=int, default=None, help="probe: the window move's width forced (0: off; default: its rule)"
    )
    parser.add_argument(
        "--profile-steps", type=int, default=None, help="probe: the profile move's steps a block (default: its own)"
    )
    parser.add_argument("--system", default="duffing", choices=tuple(QUICK_CASES), help="quick mode's system")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        worker(*args.worker)
        return 0
    args.max_time = args.max_time or (60.0 if args.quick else 180.0)
    if args.system != "duffing" and not args.quick:
        parser.error(f"--system {args.system} applies to --quick (the full grid is Duffing's)")
    quick = QUICK_CASES[args.system]
    cases = quick if args.quick else grid()
    if args.orders:
        keep = list(dict.fromkeys(o.strip() for o in args.orders.split(",")))  # "1", or "0+2": a sum
        # quick: its small case at each order asked for; the grid: the grid's cases of those orders
        cases = (
            [c._replace(order=o if "+" in o else int(o)) for o in keep for c in quick]
            if args.quick
            else [c for c in cases if str(c.order) in keep]
        )
    if args.sensors:
        if not args.quick:
            parser.error("--sensors applies to --quick (the grid spans the sensor sets itself)")
        cases = [c._replace(sensors=args.sensors) for c in cases]
    if args.start:
        if not args.quick:
            parser.error("--start applies to --quick (the grid spans the starts itself)")
        cases = [c._replace(start=args.start) for c in cases]
    for key, field in (("k3", "k3"), ("noise", "noise"), ("samples", "T")):
        if getattr(args, key) is not None:
            if not args.quick:
                parser.error(f"--{key} applies to --quick (the grid spans it itself)")
            cases = [c._replace(**{field: getattr(args, key)}) for c in cases]
    methods = [m.strip() for m in args.methods.split(",")]
    import tempfile

    t0 = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in cases:
            for method in methods:
                print(f"{case.label}: {method} ...", flush=True)
                res = run_job(case, method, args, Path(tmp))
                rows.append((case, method, res))
                print(
                    "   ",
                    {k: v for k, v in res.items() if k in ("error", "force_coverage", "converged", "wall_s")},
                    flush=True,
                )
    text = report(rows, args, time.perf_counter() - t0)
    name = (
        "nonlinear_calibration"
        if args.system == "duffing"
        else f"nonlinear_calibration_{args.system.replace('-', '_')}"
    )
    out = args.out or RESULTS_DIR / (f"{name}_quick.md" if args.quick and args.system == "duffing" else f"{name}.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(text)
    print(f"written {out}")
    return 1 if any("error" in r for _, _, r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
