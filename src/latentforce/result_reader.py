"""Reading a result folder back (:func:`read_results`): draws, sample stats, observed channels and truth
from ``posterior.nc``, state means and sds from ``summary.csv``, the scalars from ``summary.json``; the
inverse of :func:`latentforce.result_files.write_results` (whose module doc gives the layout)."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from latentforce.errors import LatentForceError
from latentforce.results import _ENGINE, _PATH_DRAW, RunResult

_COLUMN = re.compile(r"^(?P<state>.+?)(?:_(?P<index>\d+))?_(?P<kind>mean|sd)$")


def read_results(out_dir: Path) -> RunResult:
    """Read a result folder back into a :class:`RunResult`.

    Parameter and trajectory draws, sample stats, observed channels and
    truth come from ``posterior.nc``; state means and sds from
    ``summary.csv``; the scalars (log-likelihood, acceptance, seed, ...)
    from ``summary.json``. Enough to redraw every figure.
    """
    out_dir = Path(out_dir)
    nc_path, json_path, csv_path = (out_dir / n for n in ("posterior.nc", "summary.json", "summary.csv"))
    missing = [p.name for p in (nc_path, json_path) if not p.is_file()]
    if missing:
        raise LatentForceError(
            f"{str(out_dir)!r} is not a latentforce result folder: it has no "
            f"{' or '.join(missing)}. Give the --out folder of an `estimate` or `demo` run."
        )
    try:
        summary = json.loads(json_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise LatentForceError(f"Cannot read {str(json_path)!r}: {err}.") from err
    try:
        with xr.open_datatree(nc_path, engine=_ENGINE) as tree:
            tree = tree.load()
    except (OSError, ValueError) as err:
        raise LatentForceError(f"Cannot read {str(nc_path)!r} as netCDF: {err}.") from err

    attrs = tree.attrs
    posterior = _group(tree, "posterior")
    time = np.asarray(posterior["time"].values if "time" in posterior.coords else [], dtype=float)
    method = str(summary.get("method", attrs.get("method", "")))

    param_draws, path_draws = {}, {}
    for name, var in posterior.data_vars.items():
        if var.dims == ("chain", "draw"):
            param_draws[name] = np.asarray(var.values, dtype=float)
        elif var.dims[:2] in (("chain", _PATH_DRAW), ("chain", "draw")) and "time" in var.dims:
            a = np.asarray(var.values, dtype=float)
            path_draws[name] = a if a.ndim == 4 else a[..., None]

    param_chains = {
        name: np.asarray(v.values, dtype=float) for name, v in _group(tree, "parameter_chains").data_vars.items()
    }
    sample_stats = {name: np.asarray(v.values) for name, v in _group(tree, "sample_stats").data_vars.items()}
    observed_ds = _group(tree, "observed_data")
    observed = {
        str(v.attrs.get("column", name)): np.asarray(v.values, dtype=float) for name, v in observed_ds.data_vars.items()
    }
    if time.size == 0 and "time" in observed_ds.coords:
        time = np.asarray(observed_ds["time"].values, dtype=float)
    truth = {}
    for name, v in _group(tree, "constant_data").data_vars.items():
        if name.startswith("true_"):
            a = np.asarray(v.values, dtype=float)
            truth[name[len("true_") :]] = a if a.ndim == 2 else a[:, None]

    state_mean, state_sd = {}, {}
    outputs = {str(k): str((v or {}).get("unit", "")) for k, v in (summary.get("outputs") or {}).items()}
    if csv_path.is_file():
        csv_time, state_mean, state_sd = _read_summary_csv(csv_path, outputs)
        if time.size == 0:
            time = csv_time
    else:  # nothing sampled: the smoother's means and sds are in posterior.nc
        for name, v in posterior.data_vars.items():
            m = _COLUMN.match(name)
            if m and m.group("index") is None:
                a = np.asarray(v.values, dtype=float)
                target = state_mean if m.group("kind") == "mean" else state_sd
                target[m.group("state")] = a if a.ndim == 2 else a[:, None]

    def width_of(state: str, default: int) -> int:
        for source in (state_mean, truth):
            if state in source:
                return int(source[state].shape[1])
        if state in path_draws:
            return int(path_draws[state].shape[-1])
        return default

    ndof = int(attrs.get("ndof", width_of("displacement", 1)))
    nforce = int(attrs.get("nforce", width_of("force", 1)))

    return RunResult(
        method=method,
        time=time,
        ndof=ndof,
        nforce=nforce,
        state_mean=state_mean,
        state_sd=state_sd,
        param_draws=param_draws,
        param_chains=param_chains,
        path_draws=path_draws,
        sample_stats=sample_stats,
        acceptance=[float(a) if a is not None else float("nan") for a in summary.get("acceptance", [])],
        log_likelihood=_float(summary.get("log_likelihood")),
        observed=observed,
        truth=truth,
        point_estimate={k: _float(v) for k, v in (summary.get("point_estimate") or {}).items()},
        diagnostics=dict(summary.get("diagnostics") or {}),
        # posterior.nc may hold only the draws aligned with the trajectories:
        # keep the full-chain summary that was written with the run.
        param_summary=summary.get("parameters") or None,
        seed=int(summary.get("seed", attrs.get("seed", 0)) or 0),
        wall_time_s=_float(summary.get("wall_time_s", 0.0)),
        # MDOF matrices (M, C, K) are lists
        fixed={
            k: (np.asarray(v, dtype=float) if isinstance(v, list) else _float(v))
            for k, v in (summary.get("fixed") or {}).items()
        },
        convergence=None if method == "kalman" else dict(summary.get("convergence") or {}),
        units=dict((summary.get("units") or {}).get("channels") or {}),
        outputs=outputs,
        force_psd=_read_force_psd(out_dir),
    )


def _read_force_psd(out_dir: Path) -> dict | None:
    from latentforce.io.extra_results import FORCE_PSD, read_force_psd

    return read_force_psd(out_dir / FORCE_PSD)


def _float(value: Any) -> float:
    return float("nan") if value is None else float(value)


def _group(tree: xr.DataTree, name: str) -> xr.Dataset:
    if name in tree.children:
        return tree[name].to_dataset()
    return xr.Dataset()


def _read_summary_csv(path: Path, outputs=()) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        try:
            header = next(reader)
        except StopIteration:
            raise LatentForceError(f"{str(path)!r} is empty; expected a summary table.") from None
        rows = [[float(x) for x in row] for row in reader if row]
    table = np.asarray(rows, dtype=float).reshape(len(rows), len(header))
    if not header or header[0] != "time":
        raise LatentForceError(f"{str(path)!r} does not start with a 'time' column.")
    from latentforce.io.extra_results import split_output_columns

    out_mean, out_sd, used = split_output_columns(header, table, outputs)
    parts: dict[str, dict[str, dict[int, np.ndarray]]] = {}
    for j, column in enumerate(header[1:], start=1):
        m = _COLUMN.match(column)
        if m is None or j in used:
            continue
        index = int(m.group("index")) if m.group("index") is not None else 0
        parts.setdefault(m.group("kind"), {}).setdefault(m.group("state"), {})[index] = table[:, j]
    stacked = {
        kind: {s: np.column_stack([c[i] for i in sorted(c)]) for s, c in by_state.items()}
        for kind, by_state in parts.items()
    }
    return table[:, 0], {**stacked.get("mean", {}), **out_mean}, {**stacked.get("sd", {}), **out_sd}
