"""Result-folder pieces beside the states: the virtual sensors' columns and ``force_psd.csv``.

Hooks of :mod:`latentforce.results` (which owns the folder's layout):

``force_psd.csv``
    One row per frequency: ``frequency`` [Hz], ``psd_mean``, ``psd_q05``,
    ``psd_q95`` (the posterior force's one-sided Welch density and its 5 % /
    95 % quantiles over posterior sample paths, force²/Hz), ``prior_psd``
    (the GP prior's one-sided density at the posterior hyperparameters) and,
    when the truth is known, ``truth_psd`` (:mod:`latentforce.spectrum`).
Outputs
    ``NAME_mean``, ``NAME_sd`` in ``summary.csv`` and ``posterior.nc`` (the
    latter also holds sampled paths ``NAME`` under the samplers), with the
    unit as a netCDF attribute and in ``summary.json``'s ``outputs`` table.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

FORCE_PSD = "force_psd.csv"


def write_force_psd(path: Path, table: dict[str, np.ndarray]) -> None:
    """``table`` (columns of one length) as CSV at full (round-trip) precision."""
    names = list(table)
    data = np.column_stack([np.asarray(table[n], dtype=float) for n in names])
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(names)
        writer.writerows([repr(float(x)) for x in row] for row in data.tolist())


def read_force_psd(path: Path) -> dict[str, np.ndarray] | None:
    """The table :func:`write_force_psd` wrote, or ``None`` when there is none."""
    if not Path(path).is_file():
        return None
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        rows = [[float(x) for x in row] for row in reader if row]
    if not header:
        return None
    data = np.asarray(rows, dtype=float).reshape(len(rows), len(header))
    return {n: data[:, j] for j, n in enumerate(header)}


def split_output_columns(header: list[str], table: np.ndarray, outputs) -> tuple[dict, dict, set]:
    """Means and sds ``(T, 1)`` of the outputs named in ``outputs`` from ``summary.csv``
    (matched by exact name, so an output named ``drift_1`` is not read as a component),
    and the column indices used."""
    means, sds, used = {}, {}, set()
    for name in outputs:
        for kind, target in (("mean", means), ("sd", sds)):
            col = f"{name}_{kind}"
            if col in header:
                j = header.index(col)
                target[name] = table[:, j : j + 1]
                used.add(j)
    return means, sds, used
