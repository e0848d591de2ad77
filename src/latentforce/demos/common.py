"""Helpers shared by the demos: config files, tables and the run-and-write step."""

from __future__ import annotations

import contextlib
from pathlib import Path

from latentforce import estimate
from latentforce.io.config import config_from_dict
from latentforce.io.data import load_data
from latentforce.io.writers import write_csv
from latentforce.results import FIGURE_LOCK, check_out_dir, write_figures, write_results


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return repr(float(v)) if isinstance(v, float) else str(v)


def to_toml(config: dict) -> str:
    """TOML text for a config dict of our shape; ``sensors`` is an array of tables, and so is a
    section's list of tables (``[[system.elements]]``), written after the section's own keys."""
    lines = []
    nested = lambda v: isinstance(v, list) and v and all(isinstance(x, dict) for x in v)
    for section, body in config.items():
        tables = body if isinstance(body, list) else [body]
        for table in tables:
            lines.append(f"[[{section}]]" if isinstance(body, list) else f"[{section}]")
            lines.extend(f"{k} = {toml_value(v)}" for k, v in table.items() if not nested(v))
            lines.append("")
            for k, v in table.items():
                if nested(v) and not isinstance(body, list):
                    for sub in v:
                        lines.append(f"[[{section}.{k}]]")
                        lines.extend(f"{kk} = {toml_value(vv)}" for kk, vv in sub.items())
                        lines.append("")
    return "\n".join(lines)


def write_case(
    folder: Path,
    config: dict,
    columns: dict,
    *,
    overwrite: bool,
    progress=None,
    seed=0,
    diagnostics: dict | None = None,
    channels=None,
    figure_pool=None,
):
    """Write ``data.csv`` and ``config.toml``, run the estimate on them, write the results.

    ``diagnostics`` are added to the result's (e.g. the true hyperparameters, which
    the histograms then mark). ``channels``: as :func:`latentforce.estimate.run`
    (cases run side by side then compile their programs once). ``figure_pool``:
    a :func:`figure_process` pool to draw the figures in (else this thread).

    The estimate reads the data file back through the same loader as
    ``latentforce estimate``, so the demo exercises the user's path.
    """
    folder = Path(folder)
    check_out_dir(folder, overwrite)
    folder.mkdir(parents=True, exist_ok=True)
    data_file = folder / "data.csv"
    config = dict(config)
    config["data"] = dict(config["data"], path="data.csv")
    write_csv(data_file, columns)
    (folder / "config.toml").write_text(to_toml(config), encoding="utf-8")
    problem = config_from_dict(config, source=str(folder / "config.toml"), base_dir=folder)
    settings = problem.data
    dataset = load_data(
        data_file,
        problem.columns,
        time_column=settings.time_column,
        sample_rate=settings.sample_rate,
        missing=settings.missing,
    )
    result, extras = estimate.run(problem, dataset, seed=seed, progress=progress, channels=channels)
    result.diagnostics.update(diagnostics or {})
    # data.csv and config.toml are ours: the folder check above already passed.
    write_results(folder, result, overwrite=True, figures=figure_pool is None)
    if figure_pool is not None:
        from concurrent.futures.process import BrokenProcessPool

        try:
            figure_pool.submit(write_figures, folder, result).result()
        except BrokenProcessPool:  # the helper process died (e.g. out of memory): draw here
            with FIGURE_LOCK:
                write_figures(folder, result)
    return problem, dataset, result, extras


def pct_error(est: float, true: float) -> str:
    return f"{100.0 * (est - true) / true:+.1f}%"


def table(rows: list[list[str]], header: list[str]) -> str:
    widths = [max(len(str(r[i])) for r in rows + [header]) for i in range(len(header))]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths)
    out = [fmt.format(*header), fmt.format(*["-" * w for w in widths])]
    out += [fmt.format(*[str(c) for c in r]) for r in rows]
    return "\n".join(out)


def fmt(x: float) -> str:
    return f"{x:.4g}"


def run_cases_concurrently(jobs, meanwhile=None):
    """Run independent demo cases in two threads and return their results in order.

    Each case is mostly small XLA ops and compilation, which use one core; JAX
    releases the GIL while it compiles and executes, so two cases on the
    2 cores of a laptop take about the time of one. ``meanwhile()``, if
    given, runs in the calling thread while the cases run (e.g. a figure of
    the ground truth, which would otherwise add to the end of the run).
    """
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = [pool.submit(job) for job in jobs]
        if meanwhile is not None:
            meanwhile()
        return [f.result() for f in futures]


@contextlib.contextmanager
def figure_process():
    """A one-process pool, started now, in which a demo case draws its figures.

    Drawing is pure Python (matplotlib), so two cases that finish together
    draw one after the other in one process (about 4 s each); in a second
    process they draw side by side. The process is spawned (JAX's threads
    make ``fork`` unsafe) and imports the result layer at once, while the
    demo simulates its data. Yields ``None`` (draw in the thread) if no
    process can be started.
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    pool = None
    try:
        pool = ProcessPoolExecutor(
            max_workers=1, mp_context=multiprocessing.get_context("spawn"), initializer=_import_figure_modules
        )
        pool.submit(int)  # start the process (and its imports) now
    except (OSError, RuntimeError):
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
        yield None
        return
    with pool:
        yield pool


def _import_figure_modules() -> None:
    import latentforce.plots  # noqa: F401
    import latentforce.results  # noqa: F401


def preload_modules(names=("arviz", "matplotlib.figure", "matplotlib.backends.backend_agg")) -> None:
    """Import the result layer's heavier modules in a background thread.

    The samplers import ArviZ (about 3 s) and matplotlib only when a run
    ends; a demo starts this while it simulates its data (mostly compiled
    code, which leaves the interpreter free), so that the import is not
    added to the end of the run. Python's import lock makes the later
    ``import`` wait for this one if it has not finished.
    """
    import importlib
    import threading

    def _load():
        for name in names:
            try:
                importlib.import_module(name)
            except ImportError:  # the later import reports it
                pass

    threading.Thread(target=_load, name="latentforce-preload", daemon=True).start()


def noisy_record(sim, seed: int) -> tuple[dict, float, float]:
    """``(columns, acc_sd, disp_sd)`` of a single-DOF simulation: acceleration and displacement with
    1 % RMS noise each (from ``seed + 1``) and the truth columns of every state simulated."""
    import numpy as np

    rng = np.random.default_rng(seed + 1)
    acc, disp = sim.acceleration[:, 0], sim.displacement[:, 0]
    acc_sd = 0.01 * float(np.sqrt(np.mean(acc**2)))
    disp_sd = 0.01 * float(np.sqrt(np.mean(disp**2)))
    n = len(acc)
    columns = {
        "time": sim.time,
        "acc": acc + acc_sd * rng.normal(size=n),
        "disp": disp + disp_sd * rng.normal(size=n),
        "displacement": disp,
        "velocity": sim.velocity[:, 0],
    }
    if sim.hysteretic_force is not None and sim.hysteretic_force.shape[1]:
        columns["hysteretic_force"] = sim.hysteretic_force[:, 0]
    columns["force"] = sim.force[:, 0]
    return columns, acc_sd, disp_sd


def echo_truth_report(result, true_params: dict, echo, t0: float, out, where: str = "") -> None:
    """Print a demo's states against the truth (NMSE, share inside 3 sd), its sampled parameters
    against their true values (median, 90 % interval, R-hat, ESS), the run's verdict and its time."""
    import time

    import numpy as np

    from latentforce.results import coverage, nmse

    rows = []
    for state in result.truth:
        width = np.shape(result.truth[state])[1]
        for i in range(width):  # one row per DOF (per element, per force) where there are several
            x, m, s = result.truth[state][:, i], result.state_mean[state][:, i], result.state_sd[state][:, i]
            name = f"{state}_{i}" if width > 1 else state
            rows.append([name, f"{nmse(x, m):.3f}", f"{100 * coverage(x, m, s, 3.0):.1f}%"])
    echo(table(rows, ["state", "NMSE %", "truth within 3 sd"]))
    prow = []
    for n, s in (result.param_summary or {}).items():
        inside = s["q05"] <= true_params[n] <= s["q95"]
        prow.append(
            [n, fmt(true_params[n]), fmt(s["median"]), f"[{fmt(s['q05'])}, {fmt(s['q95'])}]", "yes" if inside else "NO"]
        )
        prow[-1] += [f"{s['r_hat']:.3f}", f"{s['ess_bulk']:.0f}"]
    echo(table(prow, ["parameter", "true", "median", "90% interval", "holds truth", "R-hat", "ESS"]))
    conv = result.convergence or {}
    echo(
        f"{'converged' if conv.get('converged') else 'NOT CONVERGED'}: max R-hat {conv.get('max_r_hat', np.nan):.3f}, "
        f"min bulk ESS {conv.get('min_ess_bulk', np.nan):.0f}"
    )
    echo(f"done in {time.perf_counter() - t0:.1f} s; results in {out}/{where}")
