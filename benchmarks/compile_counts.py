"""Compilations and wall time for two records of the same shape with different numbers, per method.

A campaign runs one configuration over many records; each record has its own
numbers (the system's m, c, k, k3, noise levels, hyperparameter starts). With a
static model and a numeric pytree, the second record compiles nothing: every
program takes the numbers and the data as arguments, and ``jax.jit``'s own cache
serves it. Counted with JAX's public monitoring events (backend compiles), in one
process, the persistent compile cache off.

    python benchmarks/compile_counts.py [--quick] [--methods kalman-mcmc,pgas]

Writes ``benchmarks/results/compile_counts[_quick].md``.
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import jax
import numpy as np

import latentforce
from latentforce import estimate
from latentforce.io.config import config_from_dict
from latentforce.io.data import Dataset
from latentforce.simulate import measure, simulate

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
METHODS = ("kalman", "kalman-mcmc", "kalman-nuts", "ekf", "ukf", "pgas")


class CompileCounter:
    """Backend compiles (count and seconds) since the last :meth:`reset`, from jax.monitoring."""

    def __init__(self):
        self.count, self.seconds = 0, 0.0
        jax.monitoring.register_event_duration_secs_listener(self._listen)

    def _listen(self, event, duration, **_):
        if event == COMPILE_EVENT:
            self.count += 1
            self.seconds += duration

    def reset(self):
        self.count, self.seconds = 0, 0.0


def config(method: str, record: int, quick: bool) -> dict:
    """The campaign's configuration with record ``record``'s numbers (the system's stiffness and
    damping and the noise differ; the shape is the same)."""
    nonlinear = method in ("ekf", "ukf", "pgas")
    system = {
        "type": "duffing" if nonlinear else "linear",
        "m": 1.0,
        "c": 0.4 + 0.1 * record,
        "k": 100.0 + 20.0 * record,
    }
    if nonlinear:
        system["k3"] = 1e4 * (1 + record)
    inference = {"method": method, "chains": 2, "seed": 1}
    if method == "pgas":
        inference.update(particles=16, iterations=40 if quick else 200, burn_in=20 if quick else 100)
    elif method != "kalman":
        inference.update(iterations=60 if quick else 400, burn_in=40 if quick else 200)
    force = {
        "kernel": "matern32",
        "variance": 1.0 + record,
        "lengthscale": {"prior": "lognormal", "mu": float(np.log(0.3)), "sigma": 0.5},
    }
    if method == "kalman":
        force["lengthscale"] = 0.3
    return {
        "system": system,
        "force": force,
        "sensors": [{"column": "acc", "quantity": "acceleration", "noise_std": 0.05 * (1 + record)}],
        "inference": inference,
    }


def record(problem, cfg: dict, T: int, dt: float, seed: int) -> Dataset:
    params = {k: float(v) for k, v in cfg["system"].items() if k != "type"}
    params.update(force_variance=float(cfg["force"]["variance"]), force_lengthscale=0.3)
    sim = simulate(jax.random.key(seed), problem.model, params, T, dt)
    y = measure(jax.random.key(seed + 1), sim, problem.model.sensors)
    return Dataset.from_array(y, dt, ["acc"])


def measure_method(method: str, quick: bool, counter: CompileCounter, T: int = 256, dt: float = 0.01) -> list[dict]:
    rows = []
    for r in (0, 1):
        cfg = config(method, r, quick)
        problem = config_from_dict(copy.deepcopy(cfg), source=f"record{r}.toml")
        ds = record(problem, cfg, T, dt, seed=10 + r)
        counter.reset()
        t0 = time.perf_counter()
        estimate.run(problem, ds, seed=0)
        rows.append(
            {
                "method": method,
                "record": r + 1,
                "compiles": counter.count,
                "compile_s": counter.seconds,
                "wall_s": time.perf_counter() - t0,
            }
        )
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    latentforce.enable_x64()
    jax.config.update("jax_enable_compilation_cache", False)
    counter = CompileCounter()
    rows = []
    for method in args.methods.split(","):
        rows += measure_method(method, args.quick, counter)
        for row in rows[-2:]:
            print(
                f"{row['method']:12s} record {row['record']}: {row['compiles']:4d} compiles "
                f"({row['compile_s']:.1f} s), {row['wall_s']:.1f} s",
                flush=True,
            )
    lines = [
        "# Compilations for two records of the same shape with different numbers",
        "",
        f"`python benchmarks/compile_counts.py{' --quick' if args.quick else ''}`; one process, the "
        "persistent compile cache off; backend compiles counted with `jax.monitoring`. T = 256, "
        "2 chains; each record has its own c, k (k3), noise and force variance.",
        "",
        "| method | record | compiles | compile s | wall s |",
        "|---|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {r['method']} | {r['record']} | {r['compiles']} | {r['compile_s']:.1f} | {r['wall_s']:.1f} |" for r in rows
    ]
    out = Path(args.out or Path(__file__).parent / "results" / f"compile_counts{'_quick' if args.quick else ''}.md")
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
