"""pgas on long nonlinear records with and without the window move (``inference/window_move.py``).

The case is the calibration Duffing (``nonlinear_calibration.py``: m = 1, c = 2, k = 400, k3 = 4e5,
a 70 % nonlinear share; Matérn-3/2 force, variance 100, lengthscale 0.05 s; acceleration and
displacement at 1 % noise; hyperparameters at the truth) at each record length, run through
``estimate.run`` as a user runs it, one fresh process per run (compile included), one run after
another. Each length is run with the window move at its default and with it off, at fixed counts
(1 000 iterations after 500) and "auto" (to R-hat <= 1.01 and bulk ESS >= 400, or ``--max-time``).
The table: the sweep's particle count (the run's default: 16 with the window move, 50 without), seconds,
worst bulk ESS and R-hat, the window steps' acceptance, ESS per second, and the force's coverage of the
truth (docs/nonlinear.md, "Long records: the window move" and "Long records: fewer particles").

Usage::

    PYTHONPATH=src python benchmarks/long_record.py                # T = 1 024, 2 048, 4 096 (about 25 min)
    PYTHONPATH=src python benchmarks/long_record.py --quick        # T = 2 048, fixed counts only
    PYTHONPATH=src python benchmarks/long_record.py --order 2 --lengths 4096 --modes fixed   # Matérn-5/2
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def worker(T: int, window: str, iterations: int, max_time: float, order: int = 1) -> dict:
    import nonlinear_calibration as nc

    case = nc.Case(order=order, k3=4e5, sensors="acc,disp", noise=0.01, start="rest", T=T)
    fixed = {"iterations": iterations, "burn_in": 500} if iterations else {}
    # "off": the window move's width forced to 0; "default": the run's own rule
    t0 = time.perf_counter()
    result, truth, _ = nc.estimate_case(
        case, "pgas", 0, max_time, window=0 if window == "off" else None, inference=fixed
    )
    wall = time.perf_counter() - t0
    conv = dict(result.convergence or {})
    acc = (result.diagnostics or {}).get("acceptance_window") or []
    x, mean, sd = truth["force"], result.state_mean["force"][:, 0], result.state_sd["force"][:, 0]
    return {
        "wall_s": wall,
        "converged": bool(conv.get("converged", False)),
        "max_r_hat": conv.get("max_r_hat"),
        "min_ess": conv.get("min_ess_bulk"),
        "window_acceptance": [float(a) for a in acc],
        "particles": int((result.diagnostics or {}).get("particles", 0)),
        "force_coverage": [float(100 * np.mean(np.abs(x - mean) <= k * sd)) for k in (1, 2, 3)],
    }


def run(T: int, window: str, iterations: int, max_time: float, order: int = 1) -> dict:
    args = [sys.executable, __file__, "--worker", str(T), window, str(iterations), str(max_time), str(order)]
    env = dict(os.environ, PYTHONPATH=str(HERE.parent / "src"))
    out = subprocess.run(args, capture_output=True, text=True, env=env, check=False)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode or not lines:
        raise RuntimeError(f"worker T={T} window={window} failed:\n{out.stderr[-3000:]}")
    return json.loads(lines[-1])


def table(rows, args, total: float) -> str:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    out = [
        "# pgas on long nonlinear records: the window move on and off",
        "",
        f"{time.strftime('%Y-%m-%dT%H:%M:%S')}; {platform.machine()}, {os.cpu_count()} cores, load average "
        f"{load:.2f} at the end; seed 0; one fresh process per run (compile included), one after another. "
        "Duffing m = 1, c = 2, k = 400, k3 = 4e5 (70 % nonlinear share), "
        f"Matérn-{2 * args.order + 1}/2 force (variance 100, "
        "lengthscale 0.05 s), acceleration + displacement at 1 % noise, hyperparameters at the truth, 4 chains.",
        "",
        "| T | window move | particles | iterations | s | converged | max R-hat | worst bulk ESS | ESS per s "
        "| window acceptance | force ±1/±2/±3 sd % |",
        "|---:|---|---:|---|---:|---|---:|---:|---:|---|---|",
    ]
    for (T, window, iterations), r in rows:
        acc = ", ".join(f"{a:.2f}" for a in r["window_acceptance"]) or "–"
        cov = " / ".join(f"{c:.1f}" for c in r["force_coverage"])
        its = f"{iterations} (+500)" if iterations else f'"auto" (cap {args.max_time:g} s)'
        out.append(
            f"| {T} | {window} | {r['particles']} | {its} | {r['wall_s']:.0f} "
            f"| {'yes' if r['converged'] else '**no**'} "
            f"| {r['max_r_hat']:.3f} | {r['min_ess']:.0f} | {r['min_ess'] / r['wall_s']:.2f} | {acc} | {cov} |"
        )
    out += ["", f"Total benchmark time {total:.0f} s.", ""]
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="T = 2 048, fixed counts only")
    ap.add_argument("--lengths", default=None, help="comma-separated record lengths (default 1024,2048,4096)")
    ap.add_argument("--max-time", type=float, default=600.0)
    ap.add_argument("--order", type=int, default=1, help="the force's Matérn order p (nu = p + 1/2; default 1)")
    ap.add_argument("--modes", default=None, help='"fixed", "auto" or "fixed,auto" (default both; quick: fixed)')
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--worker", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        T, window, iterations, max_time, order = args.worker
        print(json.dumps(worker(int(T), window, int(iterations), float(max_time), int(order))))
        return 0
    lengths = [int(t) for t in (args.lengths or ("2048" if args.quick else "1024,2048,4096")).split(",")]
    names = (args.modes or ("fixed" if args.quick else "fixed,auto")).split(",")
    modes = tuple({"fixed": 1000, "auto": 0}[m] for m in names)
    t0 = time.perf_counter()
    rows = []
    for T in lengths:
        for iterations in modes:
            for window in ("default", "off"):
                print(f"T={T} window {window} iterations {iterations or 'auto'} ...", flush=True)
                rows.append(((T, window, iterations), run(T, window, iterations, args.max_time, args.order)))
    text = table(rows, args, time.perf_counter() - t0)
    kernel = f"_matern{2 * args.order + 1}2" if args.order != 1 else ""
    name = "long_record" + kernel + ("_quick" if args.quick else "")
    out = args.out or HERE / "results" / f"{name}.md"
    out.write_text(text)
    print(text)
    print(f"written {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
