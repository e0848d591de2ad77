r"""Every nonlinear method against the exact smoother on linear systems (the nonlinear-posterior issue's linear suite).

On a linear system the Kalman smoother is the exact posterior. The methods a
user would run on a nonlinear one (``pgas``, ``ekf``, ``ukf``) must agree with
it there: the issue's rule is a posterior mean within 0.5 % NMSE of the exact
smoother's and a posterior sd within 10 %. For each case a record is
simulated from the continuous model (a run already in motion, so the
stationary start is right), measured with 1 % noise, and run through each
method as a user runs it (``latentforce.estimate.run`` on a config dict,
defaults otherwise: ``pgas`` with ``iterations = "auto"``).

Cases: an SDOF (m = 1, c = 2, k = 400: 3.2 Hz, 8 % damping) and a 2-DOF chain
(force at the top floor), Matérn-1/2 … 7/2 forces and sums of them
(``--orders 0+2``: a slow Matérn-1/2 term, lengthscale 0.5 s, under a fast
Matérn-5/2 one, 0.05 s, half the variance each), acceleration only and
acceleration + displacement.

Two modes:

* hyperparameters fixed at the truth: the reference is ``method = "kalman"``;
* hyperparameters inferred (``--inferred``: lognormal priors on the force
  variance and lengthscale): the reference is ``kalman-mcmc`` on the same
  priors, itself a sampler, so the comparison carries both runs' Monte Carlo
  error; the hyperparameters' posterior means and sds are compared too.

Reported per (case, method) and per state (displacement, velocity and force at
the DOF the force acts on): the NMSE of the posterior mean against the
reference's (relative to the variance of the reference mean), the mean and the
95th percentile over time of ``|sd / sd_ref - 1|``, the run's convergence
verdict, pgas's smoother-move acceptance and switch rate, and seconds.

Usage::

    python benchmarks/linear_suite.py --quick           # SDOF, Matérn-3/2, pgas (CI)
    python benchmarks/linear_suite.py                   # SDOF and 2-DOF x 4 orders x 2 sensor sets
    python benchmarks/linear_suite.py --inferred --orders 0,2
    python benchmarks/linear_suite.py --orders 0+2 --systems sdof   # a kernel sum
"""

from __future__ import annotations

import argparse
import gc
import itertools
import os
import platform
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

import latentforce

latentforce.enable_x64()  # float64; XLA's small-loop threshold before JAX starts
import jax  # noqa: E402
from nonlinear_calibration import force_table, kernel_label  # noqa: E402  (this folder: the same sum rule)

from latentforce import estimate  # noqa: E402
from latentforce.io.config import config_from_dict  # noqa: E402
from latentforce.io.data import Dataset  # noqa: E402
from latentforce.models import is_hyper_name  # noqa: E402
from latentforce.simulate import clean_signal  # noqa: E402
from latentforce.simulate import simulate as run_sim  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"
DT = 1.0 / 100.0
FORCE_VARIANCE, LENGTHSCALE = 100.0, 0.05
STATES = ("displacement", "velocity", "force")
NMSE_LIMIT, SD_LIMIT = 0.5, 0.10  # the rule: mean within 0.5 % NMSE, sd within 10 %


class Case(NamedTuple):
    system: str  # "sdof" or "2dof"
    order: str  # Matérn nu = order + 1/2; "0+2": a sum of Matérn-1/2 and 5/2 terms
    sensors: str  # "acc" or "acc,disp"
    T: int = 256

    @property
    def label(self) -> str:
        return f"{self.system}, {kernel_label(self.order)}, {self.sensors}, T={self.T}"


def system_table(case: Case) -> dict:
    if case.system == "sdof":
        return {"type": "linear", "m": 1.0, "c": 2.0, "k": 400.0}
    # two storeys, 400 N/m each, mass-proportional damping: modes at 2.0 and 5.2 Hz
    return {
        "type": "linear",
        "M": [[1.0, 0.0], [0.0, 1.0]],
        "C": [[1.5, 0.0], [0.0, 1.5]],
        "K": [[800.0, -400.0], [-400.0, 400.0]],
        "force_dofs": [force_dof(case)],
    }


def force_dof(case: Case) -> int:
    return 0 if case.system == "sdof" else 1


def sensors(case: Case) -> list[dict]:
    top = force_dof(case)
    out = [{"column": "a_top", "quantity": "acceleration", "dof": top, "noise_std": 1.0}]
    if case.system == "2dof":
        out.append({"column": "a_low", "quantity": "acceleration", "dof": 0, "noise_std": 1.0})
    if "disp" in case.sensors:
        out.append({"column": "d_top", "quantity": "displacement", "dof": top, "noise_std": 1.0})
    return out


def _hyper(value: float, inferred: bool):
    if not inferred:
        return value
    return {"prior": "lognormal", "mu": float(np.log(value)), "sigma": 0.5, "init": value}


def case_config(case: Case, method: str, inferred: bool, max_time: float) -> dict:
    inference = {"method": method}
    if method in ("pgas", "kalman-mcmc"):
        inference["max_time"] = float(max_time)
    force = force_table(case.order, FORCE_VARIANCE, LENGTHSCALE)  # a sum: per term (nonlinear_calibration)
    per_term = lambda v: [_hyper(x, inferred) for x in v] if isinstance(v, list) else _hyper(v, inferred)
    force.update(variance=per_term(force["variance"]), lengthscale=per_term(force["lengthscale"]))
    return {
        "data": {"sample_rate": 1.0 / DT},
        "system": system_table(case),
        "force": force,
        "sensors": sensors(case),
        "inference": inference,
    }


def simulate(case: Case, seed: int):
    """The noisy record ``(T, n_sensors)`` and the noise sds (1 % of each channel's rms); cut from
    motion so that the stationary start of every method is the right prior."""
    problem = config_from_dict(case_config(case, "kalman", False, 1.0))
    model = problem.model
    lead = 500
    sim = run_sim(jax.random.key(seed), model, dict(problem.fixed), case.T + lead, DT)
    clean = np.stack([clean_signal(sim, s)[lead:] for s in model.sensors], axis=1)
    noise_sd = 0.01 * clean.std(axis=0)
    rng = np.random.default_rng(seed + 1)
    return clean + rng.standard_normal(clean.shape) * noise_sd, noise_sd


def run(case: Case, method: str, inferred: bool, y, noise_sd, seed: int, max_time: float):
    cfg = case_config(case, method, inferred, max_time)
    for sensor, sd in zip(cfg["sensors"], noise_sd):
        sensor["noise_std"] = float(sd)
    problem = config_from_dict(cfg, source=f"<{case.label} {method}>")
    dataset = Dataset.from_array(y, DT, problem.columns)
    result, _ = estimate.run(problem, dataset, seed=seed)
    return result


def compare(case: Case, result, reference) -> dict:
    """Per state: NMSE [%] of the mean against the reference's; mean and 95th percentile of
    |sd ratio - 1| over time."""
    j = force_dof(case)
    out = {}
    for state in STATES:
        col = 0 if state == "force" else j
        m, s = result.state_mean[state][:, col], result.state_sd[state][:, col]
        mr, sr = reference.state_mean[state][:, col], reference.state_sd[state][:, col]
        ratio = np.abs(s / sr - 1)
        out[state] = {
            "nmse": float(100 * np.mean((m - mr) ** 2) / np.var(mr)),
            "sd_mean": float(np.mean(ratio)),
            "sd_p95": float(np.percentile(ratio, 95)),
        }
    return out


def hyper_compare(result, reference) -> str:
    """Posterior mean (sd) of each force hyperparameter, this run over the reference."""
    cells = []
    ours, ref = result.param_summary or {}, reference.param_summary or {}
    for name in ref:
        if is_hyper_name(name) and name in ours:
            a, b = ours[name], ref[name]
            short = name.removeprefix("force_").replace("variance", "var").replace("lengthscale", "ls")
            cells.append(f"{short} {a['mean']:.3g} ({a['sd']:.2g}) vs {b['mean']:.3g} ({b['sd']:.2g})")
    return "; ".join(cells) or "–"


def verdict(cmp: dict, converged: bool) -> str:
    ok = converged and all(c["nmse"] <= NMSE_LIMIT and c["sd_mean"] <= SD_LIMIT for c in cmp.values())
    return "yes" if ok else "**no**"


def fmt(x, digits=3) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "–"
    return f"{x:.{digits}g}"


def cases(quick: bool, orders, systems) -> list[Case]:
    if quick:
        return [Case("sdof", "1", "acc")]
    return [Case(s, o, sen) for s, o, sen in itertools.product(systems, orders, ("acc", "acc,disp"))]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one small case, pgas only (CI)")
    parser.add_argument("--inferred", action="store_true", help="hyperparameters inferred; reference kalman-mcmc")
    parser.add_argument("--methods", default=None, help="default pgas,ekf,ukf (quick: pgas)")
    parser.add_argument("--orders", default="0,1,2,3")
    parser.add_argument("--systems", default="sdof,2dof")
    parser.add_argument("--T", type=int, default=256)
    parser.add_argument("--max-time", type=float, default=None, help="the samplers' max_time (default 120; quick 45)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    methods = (args.methods or ("pgas" if args.quick else "pgas,ekf,ukf")).split(",")
    max_time = args.max_time or (45.0 if args.quick else 120.0)
    orders = args.orders.split(",")
    todo = [c._replace(T=args.T) for c in cases(args.quick, orders, args.systems.split(","))]
    ref_method = "kalman-mcmc" if args.inferred else "kalman"
    t_start = time.perf_counter()
    lines = []
    for case in todo:
        # each case compiles its own programs (model, kernel order, method): dropped between cases.
        # Kept, they filled the 24 GiB machine in the 13th of 16 --inferred cases (2026-12-02:
        # "LLVM compilation error: Cannot allocate memory", then a segmentation fault)
        jax.clear_caches()
        gc.collect()
        y, noise_sd = simulate(case, args.seed)
        reference = run(case, ref_method, args.inferred, y, noise_sd, args.seed, max_time)
        for method in methods:
            t0 = time.perf_counter()
            result = run(case, method, args.inferred, y, noise_sd, args.seed, max_time)
            wall = time.perf_counter() - t0
            cmp = compare(case, result, reference)
            conv = dict(result.convergence or {})
            converged = bool(conv.get("converged", method in ("ekf", "ukf") and not args.inferred))
            acc = (result.diagnostics or {}).get("acceptance_smoother")
            sw = result.sample_stats.get("switch_rate")
            cells = " | ".join(
                f"{cmp[s]['nmse']:.3g} / {cmp[s]['sd_mean']:.3f} / {cmp[s]['sd_p95']:.3f}" for s in STATES
            )
            extra = f" | {hyper_compare(result, reference)}" if args.inferred else ""
            line = (
                f"| {case.label} | {method} | {cells} | {verdict(cmp, converged)} | "
                f"{'yes' if converged else '**no**'} | {fmt(conv.get('max_r_hat'), 4)} | "
                f"{fmt(conv.get('min_ess_bulk'))} | {fmt(float(np.mean(acc)) if acc else None, 2)} | "
                f"{fmt(float(np.mean(sw)) if sw is not None and np.size(sw) else None, 2)} | {wall:.0f}{extra} |"
            )
            print(line, flush=True)
            lines.append(line)
    total = time.perf_counter() - t_start
    load = os.getloadavg()
    head = [
        f"# Nonlinear methods vs the exact answer on linear systems ({'quick' if args.quick else 'full'}, "
        f"hyperparameters {'inferred' if args.inferred else 'fixed'})",
        "",
        f"{time.strftime('%Y-%m-%dT%H:%M:%S')}; {platform.machine()}, {os.cpu_count()} cores, load average "
        f"{load[0]:.2f} at the end; seed {args.seed}; samplers' max_time {max_time:g} s; reference: "
        f"`{ref_method}`. Force variance {FORCE_VARIANCE:g}, lengthscale {LENGTHSCALE:g} s"
        + (" (lognormal priors, sigma 0.5, about the truth)" if args.inferred else " (fixed at the truth)")
        + (
            "; a kernel sum's terms: the variance split evenly, each lengthscale ten times the next's"
            if any("+" in o for o in orders)
            else ""
        )
        + f"; 1 % noise; {1 / DT:g} Hz; records cut from motion.",
        "",
        "Each state cell: NMSE of the posterior mean vs the reference's [%] / mean |sd ratio - 1| / its 95th "
        "percentile over time. Within the rule: NMSE ≤ 0.5 % and mean |sd ratio - 1| ≤ 0.10 for every state, "
        "and converged.",
        "",
        "| case | method | displacement | velocity | force | within the rule | converged | max R-hat | "
        "min bulk ESS | smoother acceptance | switch rate | s |"
        + (" hyperparameters: mean (sd) vs reference |" if args.inferred else ""),
        "|---|---|---|---|---|---|---|---:|---:|---:|---:|---:|" + ("---|" if args.inferred else ""),
    ]
    text = "\n".join(head + lines + ["", f"Total {total:.0f} s."]) + "\n"
    print(text)
    name = "linear_suite" + ("_inferred" if args.inferred else "") + ("_quick" if args.quick else "") + ".md"
    out = args.out or RESULTS_DIR / name
    out.parent.mkdir(exist_ok=True)
    out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
