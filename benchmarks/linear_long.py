r"""Benchmark: seconds to a converged linear posterior on OMA record lengths (``kalman-mcmc``, ``kalman-nuts``).

The question (issue "Linear posteriors that converge in seconds on the record
lengths OMA uses"): how long does ``latentforce.estimate.run`` take, at its
default settings (``iterations = "auto"``, 4 chains, default warm-up), to
return a *converged* parameter posterior, compilation included, and how much
memory does it take? Converged is the library's own verdict
(:mod:`latentforce.inference.convergence`): worst rank-normalised split R-hat
<= 1.01 and worst bulk ESS >= 400 over the free parameters and the log
posterior (and tail ESS >= 100).

Cases, all sampled at 50 Hz (dt = 0.02 s), Matérn-3/2 force (variance 1,
lengthscale 0.5 s), acceleration sensors with noise sd 0.05:

* **SDOF**: m = 1 (fixed), c = 0.5, k = 158 (2.0 Hz, 2 % damping), one
  accelerometer at DOF 0; four parameters inferred: c ~ logN(log 0.5, 1),
  k ~ logN(log 150, 0.5), force variance ~ logN(0, 2), force lengthscale
  ~ logN(0, 1) (inits 0.8, 120, 2, 0.3). T = 2 000, 10 000, 50 000, 200 000
  samples (40 s to 67 min).
* **3-DOF shear frame** (``masses``, ``dampings``, ``stiffnesses`` lists):
  unit floor masses (fixed), storey stiffness 400 (1.42, 3.97, 5.74 Hz) and
  storey damper 0.5 (stiffness-proportional, 0.6-2.3 % of critical), the
  force at the top floor (DOF 2), accelerometers at DOFs 0 and 2;
  T = 20 000. Eight parameters inferred: the three storey stiffnesses
  (logN(log 400, 0.5), init 300) and dampers (logN(log 0.5, 1), init 0.8) and
  the force variance and lengthscale (priors as for the SDOF case).

Data: an exact draw from the discrete linear-Gaussian form of the model at the
true parameters (``linear_gaussian`` of
:mod:`latentforce.inference.kalman_mcmc`): :math:`x_0 \sim N(m_0, P_0)`,
:math:`x_{t+1} = A x_t + N(0, Q)`, :math:`y_t = H x_t + N(0, R)`, with a
seeded NumPy generator and the eigen-decomposition square root of ``Q``
(which is only semi-definite: the mechanical states get no direct noise).
Each record is drawn once and shared by both samplers.

Each (case, sampler) runs in a fresh Python process (this script with
``--worker``), so its time includes every JAX compilation and its peak memory
(``getrusage(RUSAGE_SELF).ru_maxrss`` of that process) is its own. The time
reported is the wall time of ``estimate.run`` (``RunResult.wall_time_s``),
split into the Laplace start (L-BFGS modes and Hessians, compilation
included), the chains (compilation, warm-up, sampling and the convergence
checks between chunks) and the rest (the states' posterior mixed over the
draws, summaries). ``max_time`` (``--max-time``) bounds the sampling loop
only; it is checked between chunks after the warm-up.

Each (case, sampler) then runs once more, on a second record of the same
case and length (another draw), in another fresh process that shares the
first one's persistent compilation cache (an empty one per (case, sampler)
at the start): the cost of each further record of a campaign, what
``latentforce estimate`` pays with its cache in ~/.cache/latentforce/xla.

Usage::

    PYTHONPATH=src python benchmarks/linear_long.py                # full: all cases, both samplers
    PYTHONPATH=src python benchmarks/linear_long.py --quick        # CI: SDOF T = 2 000, kalman-mcmc
    PYTHONPATH=src python benchmarks/linear_long.py --cases sdof:50000,frame --samplers kalman-nuts
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PROCESS_T0 = time.perf_counter()

DT = 0.02  # 50 Hz
RESULTS_DIR = Path(__file__).resolve().parent / "results"
SAMPLERS = ("kalman-mcmc", "kalman-nuts")
SDOF_LENGTHS = (2_000, 10_000, 50_000, 200_000)
FRAME_LENGTH = 20_000
QUICK_CASES = ("sdof:2000",)  # CI: one case (its second record shows the cache at work)
NOISE_SD = 0.05
FORCE_VARIANCE, FORCE_LENGTHSCALE = 1.0, 0.5
SDOF_TRUTH = {"m": 1.0, "c": 0.5, "k": 158.0}
FRAME_MASS, FRAME_STOREY_K, FRAME_STOREY_C = 1.0, 400.0, 0.5
FRAME_TRUTH = {**{f"k_{i}": FRAME_STOREY_K for i in range(3)}, **{f"c_{i}": FRAME_STOREY_C for i in range(3)}}
# Quoted from the issue (not measured here): the old kalman-mcmc on SDOF T = 50 000.
BEFORE_NOTE = (
    "**Before (quoted from the issue, not measured by this script):** SDOF, T = 50 000, "
    "kalman-mcmc on the old code (fixed iterations, no Laplace start): 72 s, peak 5.2 GB, "
    "max R-hat 1.30, min bulk ESS 11, i.e. not converged."
)


# ----- the cases ----------------------------------------------------------------
def lognormal(mu: float, sigma: float, init: float) -> dict:
    return {"prior": "lognormal", "mu": float(mu), "sigma": float(sigma), "init": float(init)}


FORCE_PRIORS = {"variance": lognormal(0.0, 2.0, 2.0), "lengthscale": lognormal(0.0, 1.0, 0.3)}


def case_config(case: str, method: str | None, max_time: float) -> dict:
    """The config dict of ``case`` ("sdof" or "frame"); ``method=None``: every parameter fixed at the truth."""
    truth = method is None
    sensor = {"quantity": "acceleration", "noise_std": NOISE_SD}
    if case == "sdof":
        system = {
            "type": "linear",
            "m": SDOF_TRUTH["m"],
            "c": SDOF_TRUTH["c"] if truth else lognormal(math.log(0.5), 1.0, 0.8),
            "k": SDOF_TRUTH["k"] if truth else lognormal(math.log(150.0), 0.5, 120.0),
        }
        sensors = [{"column": "acc0", "dof": 0, **sensor}]
    elif case == "frame":
        # A shear frame: storey springs and dampers, each inferred (p = 6 + 2 force hyperparameters).
        system = {
            "type": "linear",
            "masses": [FRAME_MASS] * 3,
            "dampings": [FRAME_STOREY_C if truth else lognormal(math.log(0.5), 1.0, 0.8)] * 3,
            "stiffnesses": [FRAME_STOREY_K if truth else lognormal(math.log(400.0), 0.5, 300.0)] * 3,
            "force_dofs": [2],
        }
        sensors = [{"column": "acc0", "dof": 0, **sensor}, {"column": "acc2", "dof": 2, **sensor}]
    else:
        raise ValueError(f"unknown case {case!r}")
    force = {
        "kernel": "matern32",
        "variance": FORCE_VARIANCE if truth else FORCE_PRIORS["variance"],
        "lengthscale": FORCE_LENGTHSCALE if truth else FORCE_PRIORS["lengthscale"],
    }
    inference = {"method": "kalman"} if truth else {"method": method, "max_time": float(max_time)}
    return {
        "data": {"sample_rate": 1.0 / DT},
        "system": system,
        "force": force,
        "sensors": sensors,
        "inference": inference,
    }


def simulate(case: str, T: int, rng: np.random.Generator) -> tuple[np.ndarray, list[str]]:
    """``y`` (T, channels): an exact draw from the discrete model at the true parameters; the columns."""
    from latentforce.inference.kalman_mcmc import linear_gaussian
    from latentforce.io.config import config_from_dict

    problem = config_from_dict(case_config(case, None, 1.0), source=f"<{case} truth>")
    A, Q, H, R, m0, P0 = (np.asarray(a, dtype=float) for a in linear_gaussian(problem.model, problem.fixed, DT))

    def root(S):  # S = L L^T for a symmetric positive semi-definite S
        w, V = np.linalg.eigh(0.5 * (S + S.T))
        return V * np.sqrt(np.clip(w, 0.0, None))

    n, d = A.shape[0], H.shape[0]
    x = m0 + root(P0) @ rng.standard_normal(n)
    w = rng.standard_normal((T, n)) @ root(Q).T
    states = np.empty((T, n))
    for t in range(T):
        states[t] = x
        x = A @ x + w[t]
    y = states @ H.T + rng.standard_normal((T, d)) @ root(R).T
    return y, list(problem.columns)


def parse_case(spec: str) -> tuple[str, int]:
    """``"sdof:50000"`` -> ("sdof", 50000); ``"frame"`` -> ("frame", 20000)."""
    name, _, T = spec.partition(":")
    name = name.strip().lower()
    if name not in ("sdof", "frame"):
        raise argparse.ArgumentTypeError(f"unknown case {spec!r}: use sdof:T or frame[:T]")
    return name, int(T) if T else (FRAME_LENGTH if name == "frame" else SDOF_LENGTHS[0])


# ----- the worker: one (case, sampler) in its own process ---------------------------------
def worker(job_path: str, out_path: str) -> None:
    job = json.loads(Path(job_path).read_text())
    import jax

    import latentforce

    latentforce.enable_x64()  # float64; XLA's small-loop threshold before JAX starts
    from latentforce import estimate
    from latentforce.io.config import config_from_dict
    from latentforce.io.data import Dataset

    data = np.load(job["data"])
    y = np.asarray(data["y"], dtype=float)
    T = y.shape[0]
    problem = config_from_dict(
        case_config(job["case"], job["sampler"], job["max_time"]), source=f"<{job['case']} T={T} {job['sampler']}>"
    )
    dataset = Dataset.from_array(y, DT, data["columns"])
    from latentforce.compile import persistent_cache

    with persistent_cache(job["cache"]):
        result, _ = estimate.run(problem, dataset, seed=job["seed"])
    process_s = time.perf_counter() - PROCESS_T0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    peak_bytes = rss if sys.platform == "darwin" else rss * 1024  # bytes on macOS, KiB on Linux
    conv = dict(result.convergence or {})
    diag = result.diagnostics
    start = diag.get("start", {})
    out = {
        "wall_s": float(result.wall_time_s),
        "process_s": process_s,
        "peak_gb": peak_bytes / 1e9,
        "optimiser_s": float(start.get("seconds", float("nan"))),
        "sampler_s": float(diag.get("sampler_wall_time_s", float("nan"))),
        "draws_per_chain": int(diag.get("draws_per_chain", 0)),
        "warmup": int(diag.get("warmup", 0)),
        "chains": int(diag.get("chains", 0)),
        "mixture_draws": diag.get("mixture_draws"),
        "acceptance": float(np.mean(result.acceptance)) if len(result.acceptance) else float("nan"),
        "converged": bool(conv.get("converged", False)),
        "max_r_hat": float(conv.get("max_r_hat", float("nan"))),
        "min_ess_bulk": float(conv.get("min_ess_bulk", float("nan"))),
        "min_ess_tail": float(conv.get("min_ess_tail", float("nan"))),
        "worst": [{k: (v if isinstance(v, str) else float(v)) for k, v in w.items()} for w in conv.get("worst", [])],
        "reason": conv.get("reason"),
        "start_method": start.get("method"),
        "modes": len(start.get("modes", [])),
        "mean_integration_steps": diag.get("mean_integration_steps"),
        "divergences": diag.get("divergences"),
        "warnings": diag.get("warnings", []),
        "params": list(problem.free),
        "summary": result.param_summary or {},
        "jax": jax.__version__,
        "platform": jax.devices()[0].platform,
    }
    Path(out_path).write_text(json.dumps(out, default=float))


def run_job(case: str, T: int, sampler: str, data_file: Path, args, tmp: Path, cache: Path, tag: str = "") -> dict:
    """Run one (case, sampler) in a fresh process with JAX's persistent compilation cache in
    ``cache``; its record, or ``{"error": ...}``."""
    job = tmp / f"{case}-{T}-{sampler}{tag}.json"
    out = tmp / f"{case}-{T}-{sampler}{tag}.out.json"
    job.write_text(
        json.dumps(
            {
                "case": case,
                "sampler": sampler,
                "data": str(data_file),
                "seed": args.seed,
                "max_time": args.max_time,
                "cache": str(cache),
            }
        )
    )
    env = dict(os.environ)
    src = str(Path(__file__).resolve().parent.parent / "src")
    env["PYTHONPATH"] = src + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    limit = args.timeout if args.timeout else args.max_time + 900.0
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), "--worker", str(job), str(out)],
            capture_output=True,
            text=True,
            timeout=limit,
            env=env,
        )
    except subprocess.TimeoutExpired:
        return {"error": f"killed after {limit:.0f} s (--timeout)", "elapsed_s": time.perf_counter() - t0}
    if proc.returncode != 0 or not out.exists():
        tail = (proc.stderr or proc.stdout or "no output").strip().splitlines()
        return {
            "error": f"worker failed (exit {proc.returncode}): {tail[-1][:200] if tail else ''}",
            "traceback": "\n".join(tail[-40:]),
            "elapsed_s": time.perf_counter() - t0,
        }
    return json.loads(out.read_text())


# ----- report -----------------------------------------------------------------------
def fmt(x, digits: int = 3) -> str:
    if x is None or not np.isfinite(x):
        return "n/a"
    return f"{x:.{digits}g}" if abs(x) < 10**digits else f"{x:,.0f}"


SHORT = {"force_variance": "variance", "force_lengthscale": "lengthscale", "log_posterior": "log post."}


def result_table(rows: list[dict], max_time: float) -> list[str]:
    lines = [
        "| case | T | p | sampler | converged | s to result | optimiser s | chains s | states s "
        "| draws/chain (+warm-up) | min bulk ESS | max R-hat | bulk ESS/s | acceptance | peak GB "
        "| second record s (converged) |",
        "|---|---:|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        head = f"| {r['label']} | {r['T']:,} | {r['p']} | {r['sampler']} |"
        res = r["result"]
        if "error" in res:
            lines.append(f"{head} **failed**: {res['error']} | " + " | ".join(["–"] * 11) + " |")
            continue
        sec = r.get("second") or {"error": "not run"}
        second = "failed" if "error" in sec else f"{fmt(sec['wall_s'])} ({'yes' if sec['converged'] else '**no**'})"
        if res["converged"]:
            verdict = "yes"
        elif res["sampler_s"] >= max_time:
            verdict = f"**no**: not converged in {max_time:g} s"
        else:
            verdict = f"**no**{': ' + res['reason'] if res.get('reason') else ''}"
        worst_ess = min(res["worst"], key=lambda w: w["ess_bulk"], default=None)
        worst_rhat = max(res["worst"], key=lambda w: w["r_hat"], default=None)
        ess_name = f" ({SHORT.get(worst_ess['name'], worst_ess['name'])})" if worst_ess else ""
        rhat_name = f" ({SHORT.get(worst_rhat['name'], worst_rhat['name'])})" if worst_rhat else ""
        chains_s = res["sampler_s"] - (res["optimiser_s"] if np.isfinite(res["optimiser_s"]) else 0.0)
        lines.append(
            f"{head} {verdict} | {fmt(res['wall_s'])} | {fmt(res['optimiser_s'])} | {fmt(chains_s)} | "
            f"{fmt(res['wall_s'] - res['sampler_s'])} | {res['draws_per_chain']:,} (+{res['warmup']}) | "
            f"{fmt(res['min_ess_bulk'])}{ess_name} | {res['max_r_hat']:.3f}{rhat_name} | "
            f"{fmt(res['min_ess_bulk'] / res['wall_s'])} | {fmt(res['acceptance'], 2)} | {res['peak_gb']:.2f} | "
            f"{second} |"
        )
    return lines


def truth_of(case: str) -> dict:
    return {
        **(SDOF_TRUTH if case == "sdof" else FRAME_TRUTH),
        "force_variance": FORCE_VARIANCE,
        "force_lengthscale": FORCE_LENGTHSCALE,
    }


def recovery_table(rows: list[dict]) -> list[str]:
    """Posterior median [5 %, 95 %] of each free parameter against the truth."""
    names = []
    for r in rows:
        for n in r["result"].get("params", []):
            if n not in names:
                names.append(n)
    truth = {**truth_of("sdof"), **truth_of("frame")}
    lines = [
        "| case | T | sampler | " + " | ".join(f"{SHORT.get(n, n)} (true {truth[n]:g})" for n in names) + " |",
        "|---|---:|---|" + "---|" * len(names),
    ]
    for r in rows:
        summary = r["result"].get("summary", {})
        if not summary:
            continue
        cells = []
        for n in names:
            s = summary.get(n)
            cells.append("–" if s is None else f"{s['median']:.4g} [{s['q05']:.4g}, {s['q95']:.4g}]")
        lines.append(f"| {r['label']} | {r['T']:,} | {r['sampler']} | " + " | ".join(cells) + " |")
    return lines


def notes(rows: list[dict]) -> list[str]:
    out = []
    for r in rows:
        res = r["result"]
        where = f"{r['label']} T = {r['T']:,} {r['sampler']}"
        if "error" in res:
            out.append(
                f"- {where}: {res['error']} after {res['elapsed_s']:.0f} s."
                + ("\n\n  ```\n  " + res["traceback"].replace("\n", "\n  ") + "\n  ```" if res.get("traceback") else "")
            )
            continue
        bits = [
            f"start {res['start_method']}" + (f" ({res['modes']} mode(s))" if res["modes"] else ""),
            f"min tail ESS {fmt(res['min_ess_tail'])}",
            f"process {fmt(res['process_s'])} s incl. imports",
            f"{res['mixture_draws']} draws mixed for the states",
        ]
        if res.get("mean_integration_steps") is not None:
            bits.append(f"NUTS {res['mean_integration_steps']:.1f} steps/draw, {res['divergences']} divergences")
        out.append(f"- {where}: " + "; ".join(bits) + ".")
        for w in res.get("warnings", []):
            out.append(f"  - warning: {w}")
    return out


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--quick", action="store_true", help=f"CI mode: {', '.join(QUICK_CASES)} with kalman-mcmc only (< 2 min)"
    )
    parser.add_argument(
        "--cases",
        type=lambda s: [parse_case(c) for c in s.split(",")],
        default=None,
        help="comma-separated cases, sdof:T or frame (default: sdof:2000,sdof:10000,"
        "sdof:50000,sdof:200000,frame; with --quick: sdof:2000,sdof:10000)",
    )
    parser.add_argument(
        "--samplers",
        type=lambda s: tuple(x.strip() for x in s.split(",")),
        default=None,
        help="comma-separated methods (default kalman-mcmc,kalman-nuts; kalman-mcmc with --quick)",
    )
    parser.add_argument(
        "--max-time",
        type=float,
        default=None,
        help="[inference].max_time per run, seconds (default 600; 100 with --quick)",
    )
    parser.add_argument(
        "--timeout", type=float, default=None, help="hard limit on one worker process, seconds (default max-time + 900)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the data and of the runs")
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="Markdown output (default benchmarks/results/linear_long.md; linear_long_quick.md with --quick)",
    )
    parser.add_argument("--worker", nargs=2, metavar=("JOB", "OUT"), help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.worker:
        worker(*args.worker)
        return 0
    started = time.perf_counter()
    if args.cases:
        cases = args.cases
    elif args.quick:
        cases = [parse_case(c) for c in QUICK_CASES]
    else:
        cases = [("sdof", T) for T in SDOF_LENGTHS] + [("frame", FRAME_LENGTH)]
    samplers = args.samplers or (("kalman-mcmc",) if args.quick else SAMPLERS)
    for s in samplers:
        if s not in SAMPLERS:
            raise SystemExit(f"unknown sampler {s!r}; choose from {', '.join(SAMPLERS)}")
    if args.max_time is None:
        args.max_time = 100.0 if args.quick else 600.0

    import jax

    import latentforce

    latentforce.enable_x64()  # float64; XLA's small-loop threshold before JAX starts

    rows = []
    load_before = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for case, T in cases:
            files = []
            for r in range(2):  # the record, and a second one of the same shape (another draw)
                y, columns = simulate(case, T, np.random.default_rng([args.seed, T, int(case == "frame"), r]))
                files.append(tmp / f"{case}-{T}-{r}.npz")
                np.savez(files[-1], y=y, columns=np.array(columns))
            for sampler in samplers:
                # a fresh, empty compilation cache: the first record pays every compile, the
                # second (a new process, the same cache) what a campaign's next record pays
                cache = tmp / f"cache-{case}-{T}-{sampler}"
                print(f"running {case} T={T} {sampler} ...", file=sys.stderr, flush=True)
                res = run_job(case, T, sampler, files[0], args, tmp, cache)
                second = run_job(case, T, sampler, files[1], args, tmp, cache, "-second")
                label = "SDOF" if case == "sdof" else "3-DOF frame"
                rows.append(
                    {
                        "label": label,
                        "case": case,
                        "T": T,
                        "sampler": sampler,
                        "p": len(res.get("params", [])) or (4 if case == "sdof" else 2),
                        "result": res,
                        "second": second,
                    }
                )
                for what, rr in (("first", res), ("second", second)):
                    status = rr.get("error") or (
                        f"converged={rr['converged']} wall {rr['wall_s']:.1f} s "
                        f"ESS {rr['min_ess_bulk']:.0f} R-hat {rr['max_r_hat']:.3f}"
                    )
                    print(f"  {what}: {status}", file=sys.stderr, flush=True)

    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    jax_on = next((r["result"]["platform"] for r in rows if "platform" in r["result"]), jax.devices()[0].platform)
    frame_inferred = any(r["case"] == "frame" for r in rows)
    lines = [
        f"# Linear posteriors on long records ({'quick' if args.quick else 'full'})",
        "",
        f"Seconds to a converged posterior with `latentforce.estimate.run` at default settings "
        f'(iterations = "auto", 4 chains, default warm-up), compilation included, each run in a fresh '
        f"process; max_time = {args.max_time:g} s; 50 Hz (dt = {DT} s); data seed {args.seed}.",
        f"{datetime.datetime.now().isoformat(timespec='seconds')}; {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores, load average {load_before} at the start and {load} at the end; JAX "
        f"{jax.__version__} on {jax_on}; NumPy {np.__version__}.",
        "",
        "## Time to result",
        "",
        *result_table(rows, args.max_time),
        "",
        "Cases: SDOF (m = 1 fixed; c, k, force variance and lengthscale inferred, p = 4; one accelerometer)"
        + (
            "; 3-DOF shear frame (unit floor masses fixed; the three storey stiffnesses and dampers and "
            "the force variance and lengthscale inferred, p = 8; accelerometers at DOFs 0 and 2, force at "
            "DOF 2)"
            if frame_inferred
            else ""
        )
        + ".",
        "",
        "Columns: *converged* is the library's verdict (max R-hat <= 1.01, min bulk ESS >= 400, min tail "
        "ESS >= 100, over the parameters and the log posterior). *s to result*: wall time of "
        "`estimate.run` (`RunResult.wall_time_s`), compilation included; it splits into *optimiser s* "
        "(Laplace start: L-BFGS modes and Hessians), *chains s* (compiling, warm-up, sampling, "
        "convergence checks) and *states s* (the states' posterior mixed over the draws, summaries). "
        "*draws/chain*: kept draws per chain after the warm-up (in brackets). *min bulk ESS* and *max "
        "R-hat*: the worst quantity in brackets. *bulk ESS/s*: min bulk ESS over *s to result*. "
        "*acceptance*: mean over chains (NUTS: the mean acceptance statistic). *peak GB*: "
        "`ru_maxrss` of the run's own process (10^9 bytes), imports and data included. *second record s*: "
        "*s to result* of a second record of the same case and length (another draw), in another fresh "
        "process sharing the first's persistent compilation cache (`latentforce.compile.persistent_cache`, "
        "as `latentforce estimate` keeps in ~/.cache/latentforce/xla): what each further record of a "
        "campaign costs.",
        "",
        BEFORE_NOTE,
        "",
        *(
            [
                "## Parameter recovery",
                "",
                "Posterior median [5 %, 95 %] over all kept draws.",
                "",
                *recovery_table(rows),
                "",
            ]
            if any(r["result"].get("summary") for r in rows)
            else []
        ),
        "## Notes per run",
        "",
        *notes(rows),
        "",
        f"Total benchmark time {time.perf_counter() - started:.1f} s.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    out = args.out or RESULTS_DIR / ("linear_long_quick.md" if args.quick else "linear_long.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(f"written {out}")
    return 0 if all("error" not in r["result"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
