r"""Benchmark: the sequential Kalman recursion against the parallel-in-time one (associative scans).

What it times, per record length T, each as one compiled program (``jax.jit``),
the compile time apart:

* **log-likelihood**: the samplers' log posterior
  (:func:`latentforce.inference.kalman_mcmc.log_posterior_fn`, discretisation
  and priors included) with ``kalman = "sequential"`` and ``"parallel"``;
* **log-likelihood + gradient**: the same with its gradient in the four
  unconstrained parameters by forward mode (``jax.jacfwd``), which is what
  ``kalman-nuts`` evaluates;
* **smoother**: filter + RTS smoother at fixed parameters
  (:func:`latentforce.inference.kalman_mcmc.smooth`, method ``kalman``).

Case: SDOF (m = 1, c = 0.5, k = 158: 2 Hz, 2 % damping), Matérn-3/2 force
(variance 1, lengthscale 0.5 s), one accelerometer (noise sd 0.05), 50 Hz;
the record is drawn from the model with 1 % of its samples missing at
random, so both sides run their general (masked) recursion. Before timing,
the script checks that both give the same log-likelihood (1e-9 relative) and
smoothed means; it stops otherwise.

Each backend's numbers go to ``benchmarks/results/parallel_kalman[_quick]_<backend>.json``
and the Markdown table ``benchmarks/results/parallel_kalman[_quick].md`` is
rebuilt from every backend's JSON found there: run it on a CPU and on a GPU
machine (``benchmarks/parallel_kalman_gpu.sh``) and the table holds both;
a backend not yet run shows "pending".

Usage::

    PYTHONPATH=src python benchmarks/parallel_kalman.py            # T = 1e3, 1e4, 1e5
    PYTHONPATH=src python benchmarks/parallel_kalman.py --quick    # T = 1e3, 1e4
    PYTHONPATH=src python benchmarks/parallel_kalman.py --T 2000,50000 --repeats 5
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

RESULTS_DIR = Path(__file__).resolve().parent / "results"
DT = 0.02
OPS = ("log-likelihood", "log-likelihood + gradient", "smoother")
CHOICES = ("sequential", "parallel")
BACKENDS = ("cpu", "gpu")


def case():
    from latentforce.kernels import Matern
    from latentforce.models import LatentForceModel, Sensor
    from latentforce.priors import LogNormal
    from latentforce.systems import LinearSystem

    model = LatentForceModel(LinearSystem(), Matern(1), [Sensor("acceleration", 0, 0.05)])
    params = {"m": 1.0, "c": 0.5, "k": 158.0, "force_variance": 1.0, "force_lengthscale": 0.5}
    names = ("c", "k", "force_variance", "force_lengthscale")
    priors = (LogNormal(np.log(0.5), 1.0), LogNormal(np.log(150.0), 0.5), LogNormal(0.0, 2.0), LogNormal(0.0, 1.0))
    return model, params, names, priors


def draw_record(model, params, T: int, seed: int = 0):
    """An exact draw from the discrete model, 1 % of samples missing at random."""
    from latentforce.inference.kalman_mcmc import linear_gaussian

    A, Q, H, R, m0, P0 = (np.asarray(a) for a in linear_gaussian(model, params, DT))
    rng = np.random.default_rng(seed)
    w, V = np.linalg.eigh(Q)
    q_root = V * np.sqrt(np.clip(w, 0.0, None))
    x = m0 + np.linalg.cholesky(P0) @ rng.normal(size=m0.size)
    xs = np.empty((T, m0.size))
    for t in range(T):
        xs[t] = x
        x = A @ x + q_root @ rng.normal(size=m0.size)
    y = xs @ H.T + rng.normal(size=(T, H.shape[0])) * np.sqrt(np.diag(R))
    mask = rng.random(y.shape) >= 0.01
    return np.where(mask, y, 0.0), mask


def programs(model, params, names, priors, choice: str):
    """The three jitted programs for one choice, each ``f(x, y, mask)``."""
    import jax
    import jax.numpy as jnp

    from latentforce.inference.kalman_mcmc import log_posterior_fn, smooth

    fixed = {n: v for n, v in params.items() if n not in names}
    logpost = log_posterior_fn(model, fixed, names, priors, DT, None, False, kalman=choice)

    def smoother(x, y, mask):
        from latentforce.priors import softplus

        p = dict(fixed)
        p.update({n: softplus(x[i]) for i, n in enumerate(names)})
        sm = smooth(model, p, y, mask, DT, kalman=choice)
        return sm.means, sm.covs, sm.log_likelihood

    return {
        "log-likelihood": jax.jit(logpost),
        "log-likelihood + gradient": jax.jit(lambda x, y, m: (logpost(x, y, m), jax.jacfwd(logpost)(x, y, m))),
        "smoother": jax.jit(smoother),
        "_x": jnp.asarray(np.log(np.expm1([params[n] for n in names]))),
    }


def measure(T_list, repeats: int, save=None) -> dict:
    """Time every (T, evaluation, choice); ``save(partial_result)`` after each T (a long run
    that is stopped keeps what it measured)."""
    import jax
    import jax.numpy as jnp

    model, params, names, priors = case()
    progs = {c: programs(model, params, names, priors, c) for c in CHOICES}
    x = progs["sequential"]["_x"]
    rows = []
    for T in T_list:
        y, mask = draw_record(model, params, T)
        y, mask = jnp.asarray(y), jnp.asarray(mask)
        results = {}
        for op in OPS:
            for c in CHOICES:
                t0 = time.perf_counter()
                compiled = progs[c][op].lower(x, y, mask).compile()
                compile_s = time.perf_counter() - t0
                out = jax.block_until_ready(compiled(x, y, mask))
                times = []
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    jax.block_until_ready(compiled(x, y, mask))
                    times.append(time.perf_counter() - t0)
                results[op, c] = out
                rows.append(
                    {
                        "T": T,
                        "op": op,
                        "kalman": c,
                        "seconds": statistics.median(times),
                        "compile_s": compile_s,
                        "repeats": repeats,
                    }
                )
                print(
                    f"T={T:>7} {op:<26} {c:<10} {statistics.median(times):9.4f} s (compile {compile_s:.1f} s)",
                    flush=True,
                )
            a, b = results[op, "sequential"], results[op, "parallel"]
            ll_a = float(a if op == "log-likelihood" else a[0] if op != "smoother" else a[2])
            ll_b = float(b if op == "log-likelihood" else b[0] if op != "smoother" else b[2])
            if not abs(ll_a - ll_b) <= 1e-9 * abs(ll_a):
                raise SystemExit(f"T={T} {op}: the parallel value {ll_b!r} differs from the sequential {ll_a!r}")
            if op == "log-likelihood + gradient":
                np.testing.assert_allclose(np.asarray(b[1]), np.asarray(a[1]), rtol=1e-7)
            if op == "smoother":
                sd = np.sqrt(np.diagonal(np.asarray(a[1]), axis1=1, axis2=2))
                if not np.max(np.abs(np.asarray(a[0]) - np.asarray(b[0])) / sd) < 1e-8:
                    raise SystemExit(f"T={T}: the parallel smoother's means differ from the sequential ones")
        if save is not None:
            save({"rows": rows, "machine": machine(), "date": datetime.datetime.now().isoformat(timespec="seconds")})
    return {"rows": rows, "machine": machine(), "date": datetime.datetime.now().isoformat(timespec="seconds")}


def machine() -> str:
    import jax

    devices = ", ".join(sorted({d.device_kind for d in jax.devices()}))
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    return (
        f"{platform.machine()}, {os.cpu_count()} cores, load average {load}; JAX {jax.__version__} on "
        f"{jax.default_backend()} ({devices}); NumPy {np.__version__}"
    )


def backend_name() -> str:
    import jax

    return "gpu" if jax.default_backend() in ("gpu", "cuda", "rocm") else "cpu"


def table(results: dict, quick: bool) -> str:
    """Markdown: one row per (T, op), seconds per evaluation for each backend and choice."""
    keys = []
    for b in BACKENDS:
        for r in results.get(b, {}).get("rows", []):
            if (r["T"], r["op"]) not in keys:
                keys.append((r["T"], r["op"]))
    keys.sort(key=lambda k: (k[0], OPS.index(k[1])))

    def cell(b, T, op, c, field="seconds"):
        for r in results.get(b, {}).get("rows", []):
            if (r["T"], r["op"], r["kalman"]) == (T, op, c):
                return r[field]
        return None

    def fmt(v):
        return "pending" if v is None else f"{v:.4g}"

    def ratio(b, T, op):
        s, p = cell(b, T, op, "sequential"), cell(b, T, op, "parallel")
        return "pending" if s is None or p is None else f"{s / p:.2g}"

    lines = [
        f"# Sequential vs parallel-in-time Kalman{' (quick)' if quick else ''}",
        "",
        (
            "Seconds per evaluation (median of repeats, compile time apart), SDOF + Matérn-3/2 force, one "
            "accelerometer, 50 Hz, 1 % of samples missing at random; `benchmarks/parallel_kalman.py`. "
            "*speed-up* = sequential / parallel (above 1: the parallel scan is faster). Compile times "
            "depend strongly on the machine's load (given below)."
        ),
        "",
    ]
    for b in BACKENDS:
        info = results.get(b)
        lines.append(
            f"- {b.upper()}: "
            + (
                f"{info['date']}; {info['machine']}"
                if info
                else "pending (run `benchmarks/parallel_kalman_gpu.sh` on a GPU machine)"
            )
        )
    lines += [
        "",
        (
            "| T | evaluation | CPU sequential s | CPU parallel s | CPU speed-up | GPU sequential s | "
            "GPU parallel s | GPU speed-up | compile s CPU (seq / par) |"
        ),
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for T, op in keys:
        comp = (
            f"{fmt(cell('cpu', T, op, 'sequential', 'compile_s'))} / {fmt(cell('cpu', T, op, 'parallel', 'compile_s'))}"
        )
        lines.append(
            f"| {T:,} | {op} | {fmt(cell('cpu', T, op, 'sequential'))} "
            f"| {fmt(cell('cpu', T, op, 'parallel'))} "
            f"| {ratio('cpu', T, op)} | {fmt(cell('gpu', T, op, 'sequential'))} | "
            f"{fmt(cell('gpu', T, op, 'parallel'))} | {ratio('gpu', T, op)} | {comp} |"
        )
    lines += [
        "",
        (
            "*log-likelihood*: the samplers' log posterior (discretisation, priors, exact Kalman "
            "log-likelihood) at one parameter vector. *+ gradient*: with its gradient in the four "
            "unconstrained parameters by `jax.jacfwd` (what `kalman-nuts` evaluates). *smoother*: filter + "
            "RTS smoother, means and covariances (method `kalman`). Both recursions agree to 1e-9 "
            "relative in the log-likelihood on every row (checked by the script before timing)."
        ),
        "",
    ]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="T = 1e3 and 1e4 only")
    parser.add_argument("--T", default=None, help="comma-separated record lengths")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--table-only",
        action="store_true",
        help="rebuild the Markdown table from the JSON files already there; measure nothing",
    )
    args = parser.parse_args(argv)

    import latentforce

    latentforce.enable_x64()  # float64 (importing the package no longer switches it on)

    T_list = (
        [int(float(t)) for t in args.T.split(",")]
        if args.T
        else ([1000, 10000] if args.quick else [1000, 10000, 100000])
    )
    stem = "parallel_kalman_quick" if args.quick else "parallel_kalman"
    RESULTS_DIR.mkdir(exist_ok=True)

    def save(measured=None):
        if measured is not None:
            (RESULTS_DIR / f"{stem}_{backend_name()}.json").write_text(json.dumps(measured, indent=1) + "\n")
        results = {}
        for b in BACKENDS:
            path = RESULTS_DIR / f"{stem}_{b}.json"
            if path.exists():
                results[b] = json.loads(path.read_text())
        text = table(results, args.quick)
        (RESULTS_DIR / f"{stem}.md").write_text(text)
        return text

    if not args.table_only:
        measure(T_list, args.repeats, save)
    print(save())


if __name__ == "__main__":
    main()
