"""The result folder: :func:`write_results` turns a :class:`~latentforce.results.RunResult`
into the result folder of INTERFACE.md, :mod:`latentforce.result_reader` reads one back and
:func:`redraw` redraws it from disk (``latentforce report DIR``); figures are drawn by
:mod:`latentforce.plots`.

Result folder layout
--------------------
``posterior.nc``
    An :class:`xarray.DataTree` written with h5netcdf, readable by both
    ``arviz.from_netcdf`` and ``xarray.open_datatree``. Groups:

    ``posterior``
        Sampled scalar parameters under their config names (``k``, ``c``,
        ``force_variance``, ``force_lengthscale``, ...) with dims
        ``(chain, draw)``. Sampled trajectories ``displacement``,
        ``velocity`` and ``force`` with dims ``(chain, path_draw, time)``:
        the trajectories are thinned (a few hundred per chain at most) while
        the parameters are not, so they live on their own draw dimension
        ``path_draw`` and the parameters keep ``draw``. MDOF systems add a
        trailing ``dof`` dim to displacement and velocity; several latent
        forces add a trailing ``force_index`` dim to force.
        For ``method = "kalman"`` (and ``ekf``/``ukf`` with every parameter
        fixed) nothing is sampled: the trajectories are one chain of
        independent draws from the smoother's Gaussian
        (:mod:`latentforce.inference.smoother_draws`), and the group also
        holds the smoother's ``displacement_mean``, ``displacement_sd``,
        ``velocity_mean``, ... with dims ``(time[, dof|force_index])``.
    ``parameter_chains``
        Where ``posterior`` holds only the parameter draws stored beside the
        thinned trajectories: every sampled parameter's full post-burn-in
        chains, dims ``(chain, draw)`` (``az.summary(idata,
        group="parameter_chains")`` gives ``summary.json``'s numbers; the
        trace, histogram and pair figures are drawn from them).
    ``observed_data``
        The measured channels by column name, dim ``time``; NaN where a
        sample was missing. Where the units are known, each carries
        ``units`` (SI), ``original_units``, ``scale_to_si`` and
        ``units_source`` attributes.
    ``sample_stats``
        The sampler statistics (``accepted``, ``log_likelihood``, ...) with
        dims ``(chain, draw)``.
    ``constant_data``
        Only when the truth is known: ``true_displacement``,
        ``true_velocity``, ``true_force`` with the same trailing dims as the
        posterior trajectories.

    Root attributes record ``method``, ``ndof``, ``nforce``, ``seed`` and
    ``latentforce_version``.
``summary.csv``
    One row per time step: ``time`` then ``NAME_mean``, ``NAME_sd`` for
    displacement, velocity and force (``displacement_0_mean``, ... for MDOF;
    ``force_0_mean``, ... for several forces), written at full (round-trip)
    precision.
``summary.json``
    The layout of INTERFACE.md, plus ``point_estimate``, ``fixed``,
    ``diagnostics`` and, where known, ``units`` (``states``: the SI unit
    of each state; ``channels``: per column its SI unit, original unit,
    factor and source). Non-finite numbers are written as ``null``.
``figures/``
    PNG plots drawn by :mod:`latentforce.plots`.

I/O never does inference numerics (STYLE.md, item 7); the only numbers
computed here are posterior summaries (mean, quantiles, R-hat, ESS) and the
error measures :func:`nmse` and :func:`coverage`.
"""

from __future__ import annotations

import csv
import json
import math
import os
import threading
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from latentforce.errors import LatentForceError
from latentforce.results import (
    _ENGINE,
    _PATH_DRAW,
    _UNITS,
    RunResult,
    _as_chain_draw,
    _as_time_width,
    _component_dim,
    _ordered_states,
    _width,
    by_column,
    nmse,
    summarise_parameters,
    summary_columns,
)

# ---------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------


# held while drawing figures (here and by the demos' own figures)
FIGURE_LOCK = threading.Lock()


def write_results(out_dir: Path, result: RunResult, *, overwrite: bool = False, figures: bool = True) -> None:
    """Write ``result`` as the result folder ``out_dir`` (see module docstring).

    An existing, non-empty folder is refused unless ``overwrite``; then only
    ``posterior.nc``, ``summary.csv``, ``summary.json`` and the figures this
    module draws are replaced, and any other file in the folder is kept.
    """
    out_dir = Path(out_dir)
    check_out_dir(out_dir, overwrite)
    out_dir.mkdir(parents=True, exist_ok=True)
    tree = _to_datatree(result)
    text = _summary_json_text(result)  # before anything is written: its checks come first
    # summary.json is written last, so that a folder without it is unfinished: a run killed while it drew
    # its figures (SIGTERM, 2026-12-04) left a summary.json saying "converged" beside 3 of its 9 figures.
    # A replaced run's summary goes first for the same reason.
    (out_dir / "summary.json").unlink(missing_ok=True)
    _replace(out_dir / "posterior.nc", lambda p: tree.to_netcdf(p, engine=_ENGINE))
    try:
        _write_tables(out_dir, result)
        if figures:
            # matplotlib's state (pyplot, the mathtext parser) is not thread-safe, and the
            # demos write their cases from two threads
            with FIGURE_LOCK:
                write_figures(out_dir, result)
    finally:  # a figure that fails still leaves the run's summary (the error is reported)
        _replace(out_dir / "summary.json", lambda p: p.write_text(text, encoding="utf-8"))


def check_out_dir(out_dir: Path, overwrite: bool) -> None:
    """Refuse an existing non-empty result folder unless ``overwrite`` (run before any work)."""
    if out_dir.exists() and not out_dir.is_dir():
        raise LatentForceError(
            f"The result folder {str(out_dir)!r} is an existing file, not a folder; choose another --out."
        )
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        if (out_dir / "checkpoint.npz").is_file():  # latentforce.checkpoint.CHECKPOINT_NAME
            raise LatentForceError(
                f"The result folder {str(out_dir)!r} holds the checkpoint of an interrupted run; nothing "
                f"was written. Pass --resume {str(out_dir)!r} (with the same config) to continue it, "
                "--force to start a new run there, or choose another --out."
            )
        raise LatentForceError(
            f"The result folder {str(out_dir)!r} already exists and is not empty; "
            "nothing was written. Pass --force to replace its results (other files "
            "in it are kept) or choose another --out."
        )


def _replace(path: Path, write) -> None:
    """Write through a temporary file so a failed write leaves no half file."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _summary_json_text(result: RunResult) -> str:
    return json.dumps(_summary_json(result), indent=2, allow_nan=False) + "\n"


def _write_tables(out_dir: Path, result: RunResult) -> None:
    """summary.csv and the force spectrum's table."""
    _replace(out_dir / "summary.csv", lambda p: _write_summary_csv(p, result))
    if result.force_psd:
        from latentforce.io.extra_results import FORCE_PSD, write_force_psd

        _replace(out_dir / FORCE_PSD, lambda p: write_force_psd(p, result.force_psd))


def _write_summaries(out_dir: Path, result: RunResult) -> None:
    _write_tables(out_dir, result)
    text = _summary_json_text(result)
    _replace(out_dir / "summary.json", lambda p: p.write_text(text, encoding="utf-8"))


def write_figures(out_dir: Path, result: RunResult) -> None:
    """Draw ``result``'s figures into ``out_dir/figures`` (the stale ones removed first)."""
    from latentforce import plots

    fig_dir = out_dir / "figures"
    fig_dir.mkdir(exist_ok=True)
    for stale in (
        [fig_dir / name for name in plots.FIGURE_NAMES]
        + list(fig_dir.glob("output_*.png"))
        + list(fig_dir.glob("joint_hyperparameters_*.png"))
    ):
        if stale.is_file():
            stale.unlink()
    plots.draw_figures(result, fig_dir)


def _to_datatree(result: RunResult) -> xr.DataTree:
    from latentforce import __version__

    time = np.asarray(result.time, dtype=float)
    T = time.size
    time_coord = {"time": ("time", time, {"units": "s"})}
    groups: dict[str, xr.Dataset] = {}

    posterior = xr.Dataset(coords=time_coord)
    for name, draws in result.param_draws.items():
        posterior[name] = (("chain", "draw"), _as_chain_draw(name, draws))
    # Nothing sampled (kalman; ekf/ukf with every parameter fixed): the smoother's marginals beside
    # the paths drawn from it (inference/smoother_draws.py).
    marginals = not result.param_draws and result.method in ("kalman", "ekf", "ukf")
    if marginals:
        for state in _ordered_states(result.state_mean):
            width = _width(result, state, result.state_mean[state])
            dims = ("time",) if width == 1 else ("time", _component_dim(state))
            for kind, source in (("mean", result.state_mean), ("sd", result.state_sd)):
                a = _as_time_width(source[state], T, width, f"state_{kind}[{state!r}]")
                posterior[f"{state}_{kind}"] = (
                    dims,
                    a[:, 0] if width == 1 else a,
                    {"units": _unit(result, state), "description": f"RTS smoother {kind}"},
                )
    # INTERFACE.md: trajectories share (chain, draw) with the parameters. The
    # inference methods store both at the same iterations; only a result whose
    # counts differ falls back to a separate ``path_draw`` dimension.
    n_param = next((np.shape(v)[-1] for v in result.param_draws.values()), None)
    n_path = next((np.shape(v)[1] for v in result.path_draws.values()), None)
    path_dim = "draw" if n_param is None or n_param == n_path else _PATH_DRAW
    for state in _ordered_states(result.path_draws):
        a = np.asarray(result.path_draws[state], dtype=float)
        width = _width(result, state, a)
        if a.ndim == 3:
            a = a[..., None]
        if a.ndim != 4 or a.shape[2] != T or a.shape[3] != width:
            raise ValueError(
                f"path_draws[{state!r}] must be (chains, path_draws, {T}, {width}), "
                f"got {np.shape(result.path_draws[state])}"
            )
        dims = ("chain", path_dim, "time")
        if width > 1:
            dims += (_component_dim(state),)
        posterior[state] = (dims, a[..., 0] if width == 1 else a, {"units": _unit(result, state)})
    if not marginals:  # the virtual sensors' per-time summaries beside their paths
        for name in result.outputs:
            for kind, source in (("mean", result.state_mean), ("sd", result.state_sd)):
                if name in source:
                    posterior[f"{name}_{kind}"] = (
                        "time",
                        _as_time_width(source[name], T, 1, name)[:, 0],
                        {"units": _unit(result, name)},
                    )
    groups["posterior"] = posterior
    # the full chains, where the posterior group holds only the draws stored beside the
    # trajectories: az.summary(idata, group="parameter_chains") gives summary.json's numbers
    if result.param_chains and any(
        np.shape(v) != np.shape(result.param_draws.get(n)) for n, v in result.param_chains.items()
    ):
        groups["parameter_chains"] = xr.Dataset(
            {n: (("chain", "draw"), _as_chain_draw(n, v)) for n, v in result.param_chains.items()}
        )

    if result.observed:
        observed = xr.Dataset(coords=time_coord)
        for column, values in result.observed.items():
            v = np.asarray(values, dtype=float).ravel()
            if v.size != T:
                raise ValueError(f"observed[{column!r}] has {v.size} samples, time has {T}")
            unit = result.units.get(column)
            attrs = (
                {}
                if not unit
                else {
                    "units": unit["unit"],
                    "original_units": unit["original"],
                    "scale_to_si": unit["scale"],
                    "units_source": unit["source"],
                }
            )
            # "/" separates groups in a DataTree: a TDMS "group/channel" or HDF5 path is stored as
            # "group|channel" with its column name in the attrs.
            if "/" in column:
                attrs["column"] = column
            observed[column.replace("/", "|")] = ("time", v, attrs)
        groups["observed_data"] = observed

    if result.sample_stats:
        groups["sample_stats"] = _sample_stats_dataset(result, posterior)

    if result.truth:
        constant = xr.Dataset(coords=time_coord)
        for state in _ordered_states(result.truth):
            width = _width(result, state, result.truth[state])
            a = _as_time_width(result.truth[state], T, width, f"truth[{state!r}]")
            dims = ("time",) if width == 1 else ("time", _component_dim(state))
            constant[f"true_{state}"] = (
                dims,
                a[:, 0] if width == 1 else a,
                {"units": _unit(result, state)},
            )
        groups["constant_data"] = constant

    tree = xr.DataTree.from_dict(groups)
    tree.attrs.update(
        {
            "method": result.method,
            "ndof": int(result.ndof),
            "nforce": int(result.nforce),
            "seed": int(result.seed),
            "latentforce_version": __version__,
        }
    )
    return tree


def _sample_stats_dataset(result: RunResult, posterior: xr.Dataset) -> xr.Dataset:
    """Sample stats on (chain, draw); a length that fits neither the parameter
    nor the trajectory draws gets a draw dimension of its own."""
    draw_size = posterior.sizes.get("draw")
    path_size = posterior.sizes.get(_PATH_DRAW)
    stats = xr.Dataset()
    for name, values in result.sample_stats.items():
        a = np.asarray(values)
        if a.ndim == 1:
            stats[name] = (("chain",), a)
            continue
        if a.ndim != 2:
            raise ValueError(f"sample_stats[{name!r}] must be (chains, draws), got {a.shape}")
        if draw_size is None or a.shape[1] == draw_size:
            draw_dim = "draw"
            draw_size = a.shape[1]
        elif a.shape[1] == path_size:
            draw_dim = _PATH_DRAW
        else:
            draw_dim = f"{name}_draw"
        stats[name] = (("chain", draw_dim), a)
    return stats


def _unit(result: RunResult, state: str) -> str:
    return result.outputs.get(state, _UNITS.get(state, ""))


def _fmt(x: float) -> str:
    # repr gives the shortest string that round-trips a float64 exactly.
    return repr(float(x))


def _write_summary_csv(path: Path, result: RunResult) -> None:
    time = np.asarray(result.time, dtype=float)
    T = time.size
    columns = [time]
    for state in _ordered_states(result.state_mean):
        width = _width(result, state, result.state_mean[state])
        mean = _as_time_width(result.state_mean[state], T, width, f"state_mean[{state!r}]")
        sd = _as_time_width(result.state_sd[state], T, width, f"state_sd[{state!r}]")
        for i in range(width):
            columns += [mean[:, i], sd[:, i]]
    table = np.column_stack(columns)
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(summary_columns(result))
        writer.writerows([_fmt(x) for x in row] for row in table.tolist())


def _nmse_by_state(result: RunResult) -> dict[str, float]:
    """``summary.json``'s ``nmse``: the states in order, their shapes checked, then :func:`by_column`."""
    T = np.asarray(result.time).size
    truth, mean = {}, {}
    for state in _ordered_states(result.truth):
        if state in result.state_mean:
            width = _width(result, state, result.truth[state])
            truth[state] = _as_time_width(result.truth[state], T, width, f"truth[{state!r}]")
            mean[state] = _as_time_width(result.state_mean[state], T, width, f"state_mean[{state!r}]")
    return by_column(nmse, truth, mean)


def _summary_json(result: RunResult) -> dict:
    from latentforce import __version__

    summary: dict[str, Any] = {
        "method": result.method,
        "log_likelihood": result.log_likelihood,
        "parameters": (
            result.param_summary if result.param_summary is not None else summarise_parameters(result.param_draws)
        ),
        "acceptance": [float(a) for a in result.acceptance],
        # kalman is exact (no sampling error); a sampler is converged only by its record
        "converged": result.method == "kalman" or bool((result.convergence or {}).get("converged", False)),
        "convergence": {"exact": True} if result.method == "kalman" else (result.convergence or {}),
    }
    if result.truth:
        summary["nmse"] = _nmse_by_state(result)
    if result.units:
        # the states this result has (no hysteretic force for a structure without one)
        states = {k: v for k, v in _UNITS.items() if k in result.state_mean or k in result.path_draws}
        summary["units"] = {"states": states, "channels": dict(result.units)}
    if result.outputs:
        summary["outputs"] = {name: {"unit": unit} for name, unit in result.outputs.items()}
    summary.update(
        {
            "wall_time_s": result.wall_time_s,
            "seed": int(result.seed),
            "version": __version__,
            "point_estimate": dict(result.point_estimate),
            "fixed": dict(result.fixed),
            "diagnostics": dict(result.diagnostics),
        }
    )
    return _jsonable(summary)


def _jsonable(value: Any) -> Any:
    """Plain JSON types; NaN and infinities become ``None`` (JSON ``null``)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if value is None or isinstance(value, str):
        return value
    if isinstance(value, Path):
        return str(value)
    return str(value)


# ---------------------------------------------------------------------------
# Redrawing
# ---------------------------------------------------------------------------


def redraw(out_dir: Path) -> None:
    """Redraw ``figures/`` and rewrite ``summary.json`` and ``summary.csv``
    from what is on disk (``latentforce report DIR``); ``posterior.nc`` is
    left as it is."""
    from latentforce.result_reader import read_results

    out_dir = Path(out_dir)
    result = read_results(out_dir)
    _write_summaries(out_dir, result)
    write_figures(out_dir, result)
