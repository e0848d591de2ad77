"""Command line: ``latentforce demo | estimate | simulate | batch | report``.

A thin layer (STYLE 7): it reads files, calls the library and writes the
result folder. Every user error becomes one paragraph on stderr and a
non-zero exit code, never a traceback (set ``LATENTFORCE_DEBUG=1`` to see
tracebacks of internal errors).
"""

from __future__ import annotations

import contextlib
import functools
import os
import sys
from pathlib import Path
from typing import Optional

import typer

from latentforce.errors import LatentForceError

app = typer.Typer(
    add_completion=False,
    # help texts name config keys as [data].path: not rich markup tags (they vanished from --help)
    rich_markup_mode=None,
    no_args_is_help=True,
    help="Bayesian estimation of unmeasured forces and states of structures from measured response, "
    "with Gaussian-process latent force models.",
)


def _compilation_cache():
    """Keep compiled XLA programs between runs (JAX's persistent cache, every compile;
    :func:`latentforce.compile.persistent_cache`).

    The samplers compile a few large programs and dozens of small ones (tens
    of seconds on a laptop); caching them makes every later run with the same
    config and record shape start at once (a campaign's second record).
    ``LATENTFORCE_CACHE_DIR`` moves the cache; ``LATENTFORCE_CACHE_DIR=""``
    turns it off; an unwritable directory runs uncached.
    """
    cache = os.environ.get(
        "LATENTFORCE_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "latentforce", "xla")
    )
    if cache:
        try:
            os.makedirs(cache, exist_ok=True)
            from latentforce.compile import persistent_cache

            return persistent_cache(cache)
        except OSError:
            pass
    return contextlib.nullcontext()


#: exit code of ``estimate --strict`` for a run that did not converge
EXIT_NOT_CONVERGED = 3


def _fail(message: str, code: int = 1) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def handle_errors(fn):
    """Turn user errors into a one-paragraph message and exit code 1."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            import latentforce

            latentforce.enable_x64()
            with _compilation_cache():
                return fn(*args, **kwargs)
        except LatentForceError as err:
            _fail(str(err))
        except KeyboardInterrupt:
            _fail(
                "interrupted; nothing more was written (a sampling run that wrote a checkpoint "
                "continues with `latentforce estimate CONFIG --resume DIR`).",
                130,
            )
        except typer.Exit:
            raise
        except Exception as err:  # an internal error: say so briefly, no traceback
            if os.environ.get("LATENTFORCE_DEBUG"):
                raise
            _fail(
                f"internal error ({type(err).__name__}: {err}). This is a bug in latentforce; "
                "rerun with LATENTFORCE_DEBUG=1 for the traceback and report it.",
                2,
            )

    return wrapper


class Progress:
    """Progress on stderr (iterations, rate, ETA, acceptance); silent when stderr is not a terminal."""

    def __init__(self, label: str):
        self.label = label
        self.bar = None
        self.enabled = sys.stderr.isatty()

    def __call__(self, done: int, total: int, acceptance: float) -> None:
        if not self.enabled:
            return
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=self.label, unit="it", file=sys.stderr, leave=False)
        self.bar.update(done - self.bar.n)
        self.bar.set_postfix(acceptance=f"{acceptance:.2f}")
        if done >= total:
            self.close()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def estimate_into(
    problem,
    out: Path,
    *,
    seed: Optional[int] = None,
    force: bool = False,
    progress: Optional[Progress] = None,
    resume=None,
):
    """Read the problem's data, run its inference and write the result folder ``out``; returns the
    :class:`~latentforce.results.RunResult`. The path of ``estimate``, and of each record of ``batch``.

    An existing non-empty ``out`` is refused before any work unless ``force``. A sampling run
    checkpoints into ``out`` as it goes (:mod:`latentforce.checkpoint`); ``resume = (meta, saved)``
    (:func:`latentforce.checkpoint.open_resume` of ``out``) continues an interrupted one.
    """
    from latentforce import checkpoint as ckpt
    from latentforce import estimate as estimate_mod
    from latentforce.io.channels import load_problem_data
    from latentforce.io.config import data_sources, samples
    from latentforce.results import check_out_dir, write_results

    if resume is None:
        check_out_dir(out, force)
    source = data_sources(problem)
    # [data].path and the sensors' own paths; several rates on one grid; units to SI
    dataset = load_problem_data(problem)
    method = problem.inference.method
    checkpoint = None
    if samples(method, problem.free) or resume is not None:
        identity = ckpt.run_identity(
            problem.config_path, source, problem.inference.seed if seed is None else seed, method
        )
        if resume is not None:
            meta, saved = resume
            ckpt.check_same_run(meta, identity, out)
            message = ckpt.version_warning(meta, identity)
            if message:
                typer.echo(f"warning: {message}", err=True)
            checkpoint = ckpt.Checkpoint(
                out, identity, problem.inference.checkpoint_every, saved, sampler=meta["sampler"]
            )
        else:
            checkpoint = ckpt.open_new(out, identity, problem.inference.checkpoint_every)
    try:
        result, _ = estimate_mod.run(problem, dataset, seed=seed, progress=progress, checkpoint=checkpoint)
    except BaseException:
        if checkpoint is not None and checkpoint.created_dir and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # a new folder the failed run left empty
        raise
    finally:
        if progress is not None:
            progress.close()
    # the folder was checked (or is this run's own) before the run
    write_results(out, result, overwrite=force or checkpoint is not None)
    if checkpoint is not None:
        checkpoint.remove()
    return result


@app.command()
@handle_errors
def estimate(
    config: Path = typer.Argument(..., help="TOML configuration file."),
    data: Optional[Path] = typer.Option(None, "--data", help="Data file; overrides [data].path."),
    out: Optional[Path] = typer.Option(None, "--out", help="Result folder (default: CONFIG-NAME-results)."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Random seed; overrides [inference].seed."),
    force: bool = typer.Option(False, "--force", help="Replace the results in an existing result folder."),
    strict: bool = typer.Option(
        False, "--strict", help="Exit with code 3 when the run did not converge (the results are written all the same)."
    ),
    resume: Optional[Path] = typer.Option(
        None,
        "--resume",
        metavar="DIR",
        help="Continue the interrupted run whose result folder is DIR from its checkpoint "
        "(DIR/checkpoint.npz, written every [inference].checkpoint_every seconds); the final draws are "
        "those of an uninterrupted run. CONFIG (and --data, --seed if given) must be the run's own.",
    ),
):
    """Estimate the force, states and parameters from measured data (the main job).

    A sampling run writes a checkpoint into its result folder as it goes; if it
    is killed, `latentforce estimate CONFIG --resume DIR` continues it.
    """
    from latentforce import checkpoint as ckpt
    from latentforce.io.config import load_config

    meta = saved = None
    if resume is not None:
        if out is not None and out.resolve() != resume.resolve():
            raise LatentForceError(
                f"--resume {str(resume)!r} continues the run in that folder; --out "
                f"{str(out)!r} names another. Give only --resume."
            )
        if force:
            raise LatentForceError("--resume continues a run and --force starts one afresh; give one of them.")
        meta, saved = ckpt.open_resume(resume)
        out = resume
        # the run's own data file, wherever the config points now (not where the sensors name
        # their own files: [data].path was then not set)
        if data is None and len(meta["identity"].get("data_files") or [None]) == 1:
            data = Path(meta["identity"]["data"])
        if seed is None:
            seed = int(meta["identity"]["seed"])
    problem = load_config(config, data_override=str(data) if data is not None else None)
    out = out if out is not None else Path(f"{config.stem}-results")
    method = problem.inference.method
    result = estimate_into(
        problem,
        out,
        seed=seed,
        force=force,
        progress=Progress(method),
        resume=None if resume is None else (meta, saved),
    )
    for warning in result.diagnostics.get("warnings", []):
        typer.echo(f"warning: {warning}", err=True)
    converged = result.method == "kalman" or bool((result.convergence or {}).get("converged", False))
    resumed = "" if resume is None else " (resumed)"
    typer.echo(
        f"{method}: results written to {out}/{resumed} "
        f"(summary.csv, summary.json, posterior.nc, figures/) in {result.wall_time_s:.1f} s"
        + ("" if converged else "; NOT CONVERGED (see the warning above)")
    )
    if strict and not converged:
        raise typer.Exit(EXIT_NOT_CONVERGED)


@app.command()
@handle_errors
def simulate(
    config: Path = typer.Argument(..., help="TOML configuration file (system, force, sensors)."),
    out: Path = typer.Option(..., "--out", help="Data file to write (.csv, .h5, .mat or .nc)."),
    seed: int = typer.Option(0, "--seed", help="Random seed."),
    duration: float = typer.Option(10.0, "--duration", help="Length of the record in seconds."),
    sample_rate: Optional[float] = typer.Option(
        None, "--sample-rate", help="Samples per second (default: [data].sample_rate, else 100)."
    ),
    force: bool = typer.Option(False, "--force", help="Replace an existing file."),
):
    """Simulate measurements (with truth columns) from a configuration's model.

    Inferred parameters take their ``init`` values; the force is a sample of
    the configured GP; each sensor gets its configured noise. The structure
    starts at rest, or from a draw of ``[initial]`` where the config has one.
    """
    import jax
    import numpy as np

    from latentforce.io.channels import sensor_unit_keys, sensor_unit_scales
    from latentforce.io.config import initial_params, load_config
    from latentforce.io.data import truth_units
    from latentforce.io.units import SI_UNITS
    from latentforce.io.writers import write_data
    from latentforce.simulate import measure, truth_columns
    from latentforce.simulate import simulate as simulate_fn
    from latentforce.substeps import needed as needed_substeps

    problem = load_config(config)
    if out.is_dir():
        raise LatentForceError(
            f"--out {str(out)!r} is a folder; simulate writes one data file (.csv, .h5, .mat or .nc), "
            "e.g. --out data.csv. Nothing was written."
        )
    if out.suffix.lower() not in (".csv", ".h5", ".hdf5", ".mat", ".nc"):
        raise LatentForceError(
            f"--out {str(out)!r}: unknown extension {out.suffix!r}; simulate writes .csv, .h5, .mat or .nc. "
            "Nothing was written."
        )
    if out.exists() and not force:
        raise LatentForceError(
            f"The file {str(out)!r} already exists; nothing was written. "
            "Pass --force to replace it or choose another --out."
        )
    rate = sample_rate or problem.data.sample_rate or 100.0
    if not (rate > 0 and duration > 0):
        raise LatentForceError("--duration and --sample-rate must be positive.")
    n = int(round(duration * rate)) + 1
    params = initial_params(problem)
    key_force, key_noise = jax.random.split(jax.random.key(seed))
    # at least 8 RK4 steps a sample, more where the structure's rate needs them (latentforce.substeps)
    fine = 8 if problem.model.system.is_linear else max(8, needed_substeps(problem.model, params, 1.0 / rate))
    sim = simulate_fn(key_force, problem.model, params, n, 1.0 / rate, initial=problem.initial, substeps=fine)
    blown = ~np.all(np.isfinite(np.reshape(np.asarray(sim.displacement), (n, -1))), axis=1)
    if blown.any():  # the structure ran away (a softening spring past its turning point, an unstable system)
        t_bad = float(np.asarray(sim.time)[int(np.argmax(blown))])
        raise LatentForceError(
            f"{config}: the simulated structure's motion grew without bound (not finite from t = {t_bad:.4g} s of "
            f"{duration:g} s): with these parameters and this force it is unstable, e.g. a softening spring "
            "(negative k3) pushed past the displacement where its stiffness turns negative. Use a hardening or "
            "smaller k3, a smaller force variance, or a shorter --duration. Nothing was written."
        )
    # A sensor with a unit key: noise_std and the written channel in that unit, the model in SI.
    scales = sensor_unit_scales(problem)
    sensors = [s._replace(noise_std=s.noise_std * f) for s, f in zip(problem.model.sensors, scales)]
    y = measure(key_noise, sim, sensors)
    columns = {(problem.data.time_column or "time"): sim.time}
    columns.update({c: y[:, i] / scales[i] for i, c in enumerate(problem.columns)})
    columns.update({k: v for k, v in truth_columns(sim).items() if k not in columns})
    # unit labels (.h5/.nc attributes): a sensor's unit key, else SI, as estimate reads them back
    keys = sensor_unit_keys(problem)
    units = {c: k or SI_UNITS[s.quantity] for c, k, s in zip(problem.columns, keys, problem.model.sensors)}
    units = {**truth_units(columns), **units, (problem.data.time_column or "time"): "s"}
    try:
        out.parent.mkdir(parents=True, exist_ok=True)  # as estimate makes its --out folder's parents
    except OSError as err:
        raise LatentForceError(f"--out {str(out)!r}: its folder cannot be made ({err}). Nothing was written.") from None
    write_data(out, columns, units)
    typer.echo(
        f"wrote {n} samples at {rate:g} Hz to {out} "
        f"(channels: {', '.join(problem.columns)}; truth: {', '.join(problem.model.layout.states)})"
    )


@app.command()
@handle_errors
def demo(
    name: str = typer.Argument(..., help="oma | duffing | duffing-params | bouc-wen | frame | sine | silverbox"),
    out: Optional[Path] = typer.Option(None, "--out", help="Result folder (default: demo-NAME)."),
    quick: bool = typer.Option(False, "--quick", help="A short run (about a minute; silverbox 2-4 minutes)."),
    seed: int = typer.Option(0, "--seed", help="Random seed."),
    force: bool = typer.Option(False, "--force", help="Replace results in an existing folder."),
    paper_settings: bool = typer.Option(
        False,
        "--paper-settings",
        help="duffing, sine: the paper's fixed counts (1e5 iterations after 1e4 "
        "burn-in) instead of running until converged.",
    ),
):
    """Run a built-in case end to end: simulate, estimate, write results, print NMSE."""
    from latentforce.demos import DEMOS

    if name not in DEMOS:
        raise LatentForceError(f"Unknown demo {name!r}; available demos: {', '.join(DEMOS)}.")
    out = out if out is not None else Path(f"demo-{name}")
    kwargs = {"paper_settings": True} if paper_settings else {}
    if paper_settings and name not in ("duffing", "sine"):
        raise LatentForceError(f"--paper-settings applies to the Vibration 2020 demos (duffing, sine), not to {name}.")
    DEMOS[name](out=out, quick=quick, seed=seed, overwrite=force, echo=typer.echo, progress=Progress, **kwargs)


@app.command()
@handle_errors
def batch(
    config: Path = typer.Argument(..., help="TOML configuration file, the same for every record."),
    data: list[str] = typer.Argument(
        ..., help="Data files, folders or glob patterns (quote them: latentforce expands them itself)."
    ),
    out: Path = typer.Option(..., "--out", help="Campaign folder: one result folder per record, batch.csv, trend.png."),
    scheduler: Optional[str] = typer.Option(
        None,
        "--scheduler",
        help="Address of a running Dask scheduler (e.g. tcp://host:8786); default: a local cluster.",
    ),
    workers: Optional[int] = typer.Option(
        None,
        "--workers",
        help="Worker processes of the local cluster (default: the CPU cores, at most one per record).",
    ),
    force: bool = typer.Option(
        False, "--force", help="Replace result folders holding another config's or data's result."
    ),
    strict: bool = typer.Option(
        False,
        "--strict",
        help="Exit with code 3 when some record's run did not converge (and none failed; failures give 4).",
    ),
):
    """Estimate many records with one configuration on Dask (a campaign); reruns skip finished records."""
    from latentforce.batch import EXIT_SOME_FAILED, run_batch
    from latentforce.batch_report import not_converged

    outcome = run_batch(
        config,
        data,
        out,
        scheduler=scheduler,
        workers=workers,
        force=force,
        echo=lambda line: typer.echo(line, err=True),
    )
    done, skipped, failed = (outcome.count(s) for s in ("done", "skipped", "failed"))
    unconverged = not_converged(outcome.rows)
    if unconverged:
        names = ", ".join(r["folder"] for r in unconverged[:10]) + (" ..." if len(unconverged) > 10 else "")
        typer.echo(
            f"warning: {len(unconverged)} of the finished records did not converge ({names}): their values in "
            f"{outcome.table.name} and on the trend figure (hollow red) are not to be trusted as they stand; "
            "each folder's summary.json says which quantities (convergence) and what to try. Rerun them "
            'with a larger max_time (iterations = "auto") and --force.',
            err=True,
        )
    flagged = f" ({len(unconverged)} NOT CONVERGED)" if unconverged else ""
    typer.echo(
        f"batch: {done} done, {skipped} skipped (finished before), {failed} failed{flagged}; records in "
        f"{outcome.order} order; table {outcome.table}, trend figure {outcome.trend}"
    )
    if failed:
        raise typer.Exit(EXIT_SOME_FAILED)
    if strict and unconverged:
        raise typer.Exit(EXIT_NOT_CONVERGED)


@app.command()
@handle_errors
def report(out_dir: Path = typer.Argument(..., help="A result folder written by estimate or demo.")):
    """Redraw the figures and rewrite the summaries of a result folder."""
    from latentforce.results import redraw

    redraw(out_dir)
    typer.echo(f"redrew {out_dir}/figures and rewrote summary.csv, summary.json")


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
