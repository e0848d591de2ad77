"""The campaign's table (``DIR/batch.csv``) and trend figure (``DIR/trend.png``).

``batch.csv`` has one row per record, in the campaign's order: ``file``,
``folder``, ``timestamp`` (from the file name, ISO 8601, empty if none),
``status`` (``done``, ``failed``, ``skipped``: finished by an earlier run,
its values from then), ``error`` (the message of a failed record),
``wall_time_s`` (reading, inference and writing of the record on its
worker), ``converged``, then ``NAME_mean`` and ``NAME_sd`` for every
inferred parameter (posterior mean and standard deviation), then
``force_rms``, the root mean square over time of the posterior mean force
(``force_J_rms`` for several forces).

The trend figure draws each inferred parameter's posterior mean with a
±2 sd bar against the record (its time when the records are in time order,
its place otherwise) and the force rms below, so that a change of the
structure, e.g. a stiffness drop, shows as a step. Failed records are
marked by red dotted lines, and records whose sampler did not converge
(``converged`` false) are drawn as hollow red markers, counted in the title
(their values are not to be trusted as they stand).
"""

from __future__ import annotations

import csv
import math
import os
from datetime import datetime
from pathlib import Path

import numpy as np

TABLE_FILE = "batch.csv"
TREND_FILE = "trend.png"
_LEADING = ("file", "folder", "timestamp", "status", "error", "wall_time_s", "converged")


def table_columns(rows: list[dict]) -> list[str]:
    """The columns of ``batch.csv``: the fixed ones, the parameters' in order of first
    appearance, then the force rms."""
    params: list[str] = []
    forces: list[str] = []
    for row in rows:
        for name in row:
            if name in _LEADING or name in params or name in forces:
                continue
            (forces if name.startswith("force_") and name.endswith("_rms") or name == "force_rms" else params).append(
                name
            )
    return list(_LEADING) + params + forces


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ""
    return str(value)


def write_table(out: Path, rows: list[dict]) -> Path:
    """Write ``out/batch.csv`` (through a temporary file renamed over it)."""
    columns = table_columns(rows)
    path = out / TABLE_FILE
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for row in rows:
            writer.writerow([_cell(row.get(c)) for c in columns])
    os.replace(tmp, path)
    return path


def _parameters(rows: list[dict]) -> list[str]:
    """The inferred parameters: the names with both a ``NAME_mean`` and a ``NAME_sd`` column."""
    columns = table_columns(rows)
    return [c[: -len("_mean")] for c in columns if c.endswith("_mean") and c[: -len("_mean")] + "_sd" in columns]


def not_converged(rows: list[dict]) -> list[dict]:
    """The finished records (``done`` or ``skipped``) whose run did not converge."""
    return [
        r for r in rows if r.get("status") in ("done", "skipped") and str(r.get("converged")).lower() in ("false", "0")
    ]


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def write_trend(out: Path, rows: list[dict], *, order: str, title: str = "") -> Path:
    """Draw ``out/trend.png`` (module doc); ``order`` is ``"time"`` or ``"file"``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    params = _parameters(rows)
    rms = [c for c in table_columns(rows) if c == "force_rms" or (c.startswith("force_") and c.endswith("_rms"))]
    panels = [(p, f"{p}_mean", f"{p}_sd") for p in params] + [(c.replace("_", " "), c, None) for c in rms]
    if order == "time":
        x = [datetime.fromisoformat(r["timestamp"]) for r in rows]
    else:
        x = list(range(1, len(rows) + 1))
    ok = np.array([r.get("status") in ("done", "skipped") for r in rows])
    failed = [xi for xi, r in zip(x, rows) if r.get("status") == "failed"]
    unconverged = {id(r) for r in not_converged(rows)}
    bad = np.array([id(r) in unconverged for r in rows])

    n = max(len(panels), 1)
    fig = Figure(figsize=(8.0, 1.0 + 2.0 * n), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    if not panels:
        axes[0].text(
            0.5,
            0.5,
            "no finished record" if not ok.any() else "no parameter inferred",
            ha="center",
            va="center",
            transform=axes[0].transAxes,
        )
    for ax, (label, mean_col, sd_col) in zip(axes, panels):
        mean = np.array([_number(r.get(mean_col)) for r in rows])
        sd = np.array([_number(r.get(sd_col)) for r in rows]) if sd_col else None
        keep = ok & np.isfinite(mean)
        xs = [xi for xi, k in zip(x, keep) if k]
        if sd is not None:
            ax.errorbar(
                xs,
                mean[keep],
                yerr=2.0 * np.nan_to_num(sd[keep]),
                fmt="o-",
                ms=4,
                capsize=3,
                color="C0",
                label="posterior mean ± 2 sd",
            )
        else:
            ax.plot(xs, mean[keep], "o-", ms=4, color="C1")
        if (keep & bad).any():  # over the line: hollow red rings on the records to distrust
            ax.plot(
                [xi for xi, k in zip(x, keep & bad) if k],
                mean[keep & bad],
                "o",
                ms=8,
                mfc="none",
                mec="red",
                mew=1.5,
                ls="none",
                label="NOT CONVERGED",
            )
        for xi in failed:
            ax.axvline(xi, color="red", ls=":", lw=1.0)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if panels and params:
        axes[0].legend(loc="best", fontsize="small")
    if order == "time":
        axes[-1].set_xlabel("record time (from the file names)")
        fig.autofmt_xdate()
    else:
        axes[-1].set_xlabel("record (file order)")
        if len(rows) <= 30:
            axes[-1].set_xticks(x, [r["folder"] for r in rows], rotation=45, ha="right", fontsize="small")
    fails = f", {len(failed)} failed (red dotted)" if failed else ""
    fails += f", {int(bad.sum())} NOT CONVERGED (hollow red)" if bad.any() else ""
    fig.suptitle(f"{title}{fails}" if title else f"{len(rows)} records{fails}")
    path = out / TREND_FILE
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=100)
    os.replace(tmp, path)
    return path
