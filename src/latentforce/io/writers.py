"""Writing channels in the formats :mod:`latentforce.io.data` reads (``simulate``'s files, the demos'
records): CSV, HDF5, MATLAB and netCDF, with each variable's unit label where the format has a place."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from latentforce.errors import LatentForceError

__all__ = ["write_csv", "write_data"]


def write_csv(path: str | Path, columns: dict[str, np.ndarray]) -> None:
    """Write equal-length 1-D ``columns`` to a CSV file with a header row.

    Values are written with Python's shortest round-trip ``repr``, so reading
    the file back gives the same float64 numbers bit for bit.
    """
    names = list(columns)
    arrays = [np.asarray(columns[n], dtype=np.float64).reshape(-1) for n in names]
    lengths = {a.size for a in arrays}
    if len(lengths) > 1:
        raise ValueError(f"columns differ in length: { {n: a.size for n, a in zip(names, arrays)} }")
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(names)
        for row in zip(*(a.tolist() for a in arrays)):
            writer.writerow([repr(v) for v in row])


def write_data(path: str | Path, columns: dict[str, np.ndarray], units: dict[str, str] | None = None) -> None:
    """Write channels in the format given by the extension (the formats ``load_data`` reads).

    ``.csv``: header row; ``.h5``/``.hdf5``: one dataset per column;
    ``.mat``: MATLAB v5, one variable per column; ``.nc``: netCDF, one
    variable per column on the dimension ``time``. ``units``: column -> unit
    label, written as each variable's ``units`` attribute in ``.h5`` and
    ``.nc`` files (the other formats have no place for it).
    """
    units = units or {}
    path = Path(path)
    ext = path.suffix.lower()
    arrays = {n: np.asarray(v, dtype=np.float64).reshape(-1) for n, v in columns.items()}
    if ext == ".csv":
        write_csv(path, arrays)
    elif ext in (".h5", ".hdf5"):
        import h5py

        with h5py.File(path, "w") as f:
            for n, a in arrays.items():
                f.create_dataset(n, data=a)
                if n in units:
                    f[n].attrs["units"] = units[n]
    elif ext == ".mat":
        from scipy.io import savemat

        savemat(path, {n: a[:, None] for n, a in arrays.items()})
    elif ext == ".nc":
        import xarray as xr

        variables = {n: ("time", a, {"units": units[n]} if n in units else {}) for n, a in arrays.items()}
        xr.Dataset(variables).to_netcdf(path, engine="h5netcdf")
    else:
        raise LatentForceError(
            f"Cannot write {str(path)!r}: unknown extension {ext!r}. Supported: .csv, .h5, .hdf5, .mat, .nc."
        )
