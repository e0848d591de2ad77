"""Measured data in and out: channels over an evenly sampled time axis.

``load_data`` reads the sensor channels named in the config from a CSV file
(header row), an HDF5 file (one 1-D dataset per channel, nested paths such as
``"group/acc"`` allowed), a MATLAB file (v5 via :func:`scipy.io.loadmat`, v7.3
via h5py since those are HDF5 files) or a netCDF file (variables by name). It
checks everything a user can get wrong (missing file or column, text in a
numeric column, NaN/inf, an uneven time axis, channels of different lengths)
and turns each into a one-paragraph :class:`~latentforce.errors.LatentForceError`
naming the file and the column. Truth columns (``displacement``,
``velocity``, ``force``, or with ``_0``, ``_1`` ... suffixes for MDOF), as
written by ``simulate``, are picked up when present for the NMSE table.
A netCDF or HDF5 variable's ``units`` attribute is its unit label: the time
column and truth columns are scaled to seconds and SI here, the sensor
channels by :mod:`latentforce.io.channels` (which knows their quantities).

This module only moves numbers between files and arrays; it does no
numerics beyond the checks (STYLE.md, rule 7).
"""

from __future__ import annotations

import csv
import difflib
import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from latentforce.errors import LatentForceError

__all__ = [
    "Dataset",
    "SUPPORTED_EXTENSIONS",
    "TRUTH_NAMES",
    "check_file",
    "load_data",
    "read_table",
    "truth_units",
]

SUPPORTED_EXTENSIONS = (".csv", ".h5", ".hdf5", ".mat", ".nc", ".uff", ".unv", ".tdms")
# Vendor formats (io/vendor.py): each channel carries its own time axis and unit.
_VENDOR_EXTENSIONS = (".uff", ".unv", ".tdms")
TRUTH_NAMES = ("displacement", "velocity", "force")
_TRUTH_PATTERN = re.compile(r"^(displacement|velocity|hysteretic_force|force)(_\d+)?$")
#: the SI unit of each truth column (what the estimates are in)
_TRUTH_SI = {"displacement": "m", "velocity": "m/s", "hysteretic_force": "N", "force": "N"}
# Relative tolerance on the spread of the time steps: tighter than any
# sensible acquisition jitter, looser than float64 round-off of t = i * dt.
# Stamps stored coarser than that (float32, or absolute epoch seconds: 2.4e-7 s
# apart at 1.7e9 s) are allowed their storage resolution too (_resolution).
_UNEVEN_RTOL = 1e-6


class Dataset(NamedTuple):
    """Measured channels on an even time grid.

    ``values[:, j]`` is channel ``columns[j]`` (NaN where not observed) and
    ``mask[:, j]`` is True where it was observed. ``truth`` maps truth column
    names found in the file to their ``(T,)`` arrays.
    """

    time: np.ndarray  # (T,)
    dt: float
    values: np.ndarray  # (T, n_channels) float64
    mask: np.ndarray  # (T, n_channels) bool
    columns: list[str]
    truth: dict[str, np.ndarray]
    #: column -> :class:`~latentforce.io.units.ChannelUnit` (the unit the numbers were given in,
    #: the SI unit they now carry, the factor); None when no units were resolved (``load_data``
    #: on a table format: the numbers are taken as SI)
    units: dict | None = None
    #: warnings from reading the file(s), for the run's own (a truth column left out, :func:`_truth_in_si`)
    notes: tuple[str, ...] = ()

    @classmethod
    def from_array(cls, values, dt: float, columns) -> "Dataset":
        """A record held in memory: ``values[:, j]`` is channel ``columns[j]`` in SI units, sampled
        every ``dt`` seconds from t = 0, observed wherever it is finite (NaN elsewhere, as a file
        read with ``missing = "skip"``); no truth columns."""
        values = np.array(values, dtype=float)
        mask = np.isfinite(values)
        values[~mask] = np.nan
        return cls(np.arange(values.shape[0]) * dt, float(dt), values, mask, list(columns), {})


# ----- readers: one per format, each a table of named 1-D channels -----------
class _Table:
    """Channels of one file: ``names`` and ``read(name) -> 1-D array``.

    ``row_label(i)`` says where data row ``i`` lives in the file, so messages
    point at a line a user can find (CSV) or an index (array formats).
    """

    names: list[str]

    def read(self, name: str) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def row_label(self, i: int) -> str:
        return f"row {i}"

    def unit(self, name: str) -> str | None:
        """The unit label the file gives channel ``name`` (None: none)."""
        return None

    def close(self) -> None:
        pass


def _err(path: Path, message: str) -> LatentForceError:
    return LatentForceError(f"data file {str(path)!r}: {message}")


def _suggest(name: str, names: list[str]) -> str:
    close = difflib.get_close_matches(name, names, n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


class _CsvTable(_Table):
    def __init__(self, path: Path):
        self.path = path
        # utf-8-sig drops the byte-order mark spreadsheet programs add.
        with open(path, newline="", encoding="utf-8-sig") as f:
            # skipinitialspace: a header like `time, "acc"` (a space before a quoted name) reads as `acc`
            rows = list(csv.reader(f, skipinitialspace=True))
        # Blank lines (e.g. a trailing newline pair) are not data.
        numbered = [(i + 1, r) for i, r in enumerate(rows) if any(cell.strip() for cell in r)]
        if not numbered:
            raise _err(path, "the file is empty (a CSV data file needs a header row and data rows)")
        _, header = numbered[0]
        self.names = [h.strip() for h in header]
        self._lines = [n for n, _ in numbered[1:]]
        self._rows = [r for _, r in numbered[1:]]
        if not self._rows:
            raise _err(path, "the file has a header row but no data rows")
        for line, row in zip(self._lines, self._rows):
            if len(row) != len(self.names):
                hint = ""
                if len(self.names) == 1 and len(row) > 1:
                    hint = (
                        f"; the header (line {numbered[0][0]}: {header[0][:40]!r}) is read as one field: is it a "
                        "comment or title line? The first non-blank line must be the header, and fields are "
                        "separated by commas"
                    )
                elif len(row) == 1 and len(self.names) > 1:
                    hint = "; are the fields separated by something other than commas (semicolons, tabs)?"
                raise _err(path, f"line {line} has {len(row)} fields but the header has {len(self.names)}{hint}")
        dupes = sorted({n for n in self.names if self.names.count(n) > 1})
        if dupes:
            raise _err(path, f"the header names column(s) {', '.join(map(repr, dupes))} more than once")

    def row_label(self, i: int) -> str:
        return f"row {i} (line {self._lines[i]} of the file)"

    def read(self, name: str) -> np.ndarray:
        j = self.names.index(name)
        out = np.empty(len(self._rows))
        for i, row in enumerate(self._rows):
            cell = row[j].strip()
            # An empty cell is a missing sample, treated like NaN.
            if not cell:
                out[i] = math.nan
                continue
            try:
                out[i] = float(cell)
            except ValueError:
                raise _err(
                    self.path, f"column {name!r} holds a non-numeric entry {cell!r} at {self.row_label(i)}"
                ) from None
        return out


class _Hdf5Table(_Table):
    """HDF5 (and MATLAB v7.3) files: every dataset, by its path inside the file."""

    def __init__(self, path: Path, skip_prefix: str | None = None):
        import h5py

        self.path = path
        self._file = h5py.File(path, "r")
        names: list[str] = []

        def visit(name, obj):
            # MATLAB v7.3 keeps cell/struct internals under "#refs#"; not channels.
            if isinstance(obj, h5py.Dataset) and not (skip_prefix and name.startswith(skip_prefix)):
                names.append(name)

        self._file.visititems(visit)
        self.names = names

    def read(self, name: str) -> np.ndarray:
        return np.asarray(self._file[name][()])

    def unit(self, name: str) -> str | None:
        return _unit_attribute(self._file[name].attrs)

    def close(self) -> None:
        self._file.close()


class _DictTable(_Table):
    def __init__(self, arrays: dict[str, np.ndarray], units: dict[str, str | None] | None = None):
        self._arrays = arrays
        self._units = units or {}
        self.names = list(arrays)

    def read(self, name: str) -> np.ndarray:
        return np.asarray(self._arrays[name])

    def unit(self, name: str) -> str | None:
        return self._units.get(name)


def _unit_attribute(attrs) -> str | None:
    """A variable's unit label: its attribute ``units`` or ``unit``, in any case (``Units``: some
    acquisition exports), "units" first; None where there is none."""
    keys = {str(k).lower(): k for k in attrs.keys()}
    return next((_label(attrs[keys[k]]) for k in ("units", "unit") if k in keys), None)


def _label(value) -> str | None:
    """An attribute's text (HDF5 stores it as str, bytes or a one-element array)."""
    value = np.asarray(value).reshape(-1)[0] if np.ndim(value) else value
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return str(value) if isinstance(value, (str, np.str_)) else None


def _open_mat(path: Path) -> _Table:
    import h5py
    from scipy import io as sio

    try:
        contents = sio.loadmat(path)
    except (NotImplementedError, ValueError) as exc:
        # v7.3 files are HDF5; loadmat refuses them with NotImplementedError
        # (or ValueError when the MATLAB header is absent).
        if h5py.is_hdf5(path):
            return _Hdf5Table(path, skip_prefix="#")
        raise _err(path, f"not a readable MATLAB file ({exc})") from None
    return _DictTable({k: v for k, v in contents.items() if not k.startswith("__")})


def _open_netcdf(path: Path) -> _Table:
    import xarray as xr

    reasons: dict[str, str] = {}
    # h5netcdf reads netCDF-4 (HDF5), scipy netCDF-3 (classic); netCDF4 either, where installed
    for engine in ("h5netcdf", "scipy", "netcdf4"):
        try:
            # decode_timedelta=False: a variable in "s" stays seconds (its label read below)
            ds = xr.open_dataset(path, engine=engine, decode_timedelta=False)
        except (ValueError, OSError, ImportError, TypeError) as exc:
            reasons[engine] = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            continue
        try:
            names = list(ds.data_vars) + list(ds.coords)
            arrays = {str(n): ds[n].values for n in names}
            units = {str(n): u for n in names if (u := _unit_attribute(ds[n].attrs)) is not None}
        finally:
            ds.close()
        return _DictTable(arrays, units)
    listing = "; ".join(f"{engine}: {why}" for engine, why in reasons.items())
    raise _err(path, f"not a readable netCDF file (each reader's reason: {listing})")


def _open(path: Path) -> _Table:
    ext = path.suffix.lower()
    try:
        if ext == ".csv":
            return _CsvTable(path)
        if ext in (".h5", ".hdf5"):
            return _Hdf5Table(path)
        if ext == ".mat":
            return _open_mat(path)
        if ext == ".nc":
            return _open_netcdf(path)
    except LatentForceError:
        raise
    except (OSError, UnicodeDecodeError) as exc:
        raise _err(path, f"cannot be read as a {ext} file ({exc})") from None
    raise _err(path, f"unknown file type {ext or '(no extension)'!r}; supported: {', '.join(SUPPORTED_EXTENSIONS)}")


def _as_vector(path: Path, name: str, raw: np.ndarray) -> np.ndarray:
    """A float64 1-D channel, or a LatentForceError naming the column."""
    arr = np.asarray(raw)
    if np.issubdtype(arr.dtype, np.datetime64) or np.issubdtype(arr.dtype, np.timedelta64):
        # netCDF time coordinates decode to datetimes: make them seconds.
        arr = (arr - arr.reshape(-1)[0]) / np.timedelta64(1, "s") if arr.size else arr.astype(float)
    # MATLAB and HDF5 store vectors as (1, T) or (T, 1) matrices.
    arr = np.squeeze(arr)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise _err(path, f"column {name!r} is not a 1-D channel (shape {tuple(np.shape(raw))})")
    if arr.dtype.kind not in "biuf":
        raise _err(path, f"column {name!r} holds non-numeric data (type {arr.dtype})")
    return arr.astype(np.float64)


def _in_unit(path: Path, table: _Table, name: str, values: np.ndarray, si: str, what: str) -> np.ndarray:
    """``values`` of column ``name`` in ``si``, by the file's unit label (as they are without one)."""
    from latentforce.io.units import NO_UNIT, unit_scale

    label = table.unit(name)
    if label is None or label.strip().lower() in NO_UNIT:
        return values
    label = label.split(" since ")[0]  # CF time: "seconds since 2024-01-01" (not decoded in HDF5)
    try:
        scale = unit_scale(label, si)
    except ValueError as exc:
        raise _err(
            path,
            f"column {name!r} has the unit label {label!r} (its 'units' attribute), which does not fit {what} "
            f"({exc}); it needs a unit like {si!r}. Correct or remove the label"
            + (
                ", or give [data].sample_rate to use an even time axis instead of this column."
                if si == "s"
                else f" (a {name!r} column is read as the truth, only to score the estimate: renaming it keeps it out)."
            ),
        ) from None
    return values * scale if scale != 1.0 else values


def _first(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _resolution(raw: np.ndarray, t: np.ndarray) -> float:
    """The spacing of the stored time stamps ``raw`` (as read) near their largest value, in the
    seconds of ``t``: the round-off a step between two of them can carry, twice over."""
    raw = np.asarray(raw)
    if raw.dtype.kind in "mM":  # integer nanoseconds (or coarser) since an epoch
        return 1e-9
    dtype = raw.dtype if raw.dtype.kind == "f" else np.dtype(np.float64)
    big = np.max(np.abs(raw[np.isfinite(raw)])) if raw.size and np.isfinite(raw).any() else 0.0
    scale = float(np.max(np.abs(t))) / float(big) if big and np.max(np.abs(t)) else 1.0
    return 2.0 * float(np.spacing(dtype.type(big))) * scale


def _check_time(path: Path, table: _Table, name: str, t: np.ndarray, resolution: float = 0.0) -> float:
    """Check the time column is finite, increasing and even (to ``_UNEVEN_RTOL`` of a step, or the
    stamps' storage ``resolution`` where coarser); return the step."""
    bad = ~np.isfinite(t)
    if bad.any():
        raise _err(path, f"time column {name!r} holds NaN/inf at {table.row_label(_first(bad))}")
    d = np.diff(t)
    if np.any(d <= 0):
        i = _first(d <= 0) + 1
        raise _err(
            path,
            f"time column {name!r} is not increasing at {table.row_label(i)} "
            f"({float(t[i - 1]):.9g} then {float(t[i]):.9g})",
        )
    dt = float(np.median(d))
    off = np.abs(d - dt) > max(_UNEVEN_RTOL * dt, 2.0 * resolution)
    if resolution > _UNEVEN_RTOL * dt:  # stamps coarser than the tolerance: the mean step is the step
        dt = float(t[-1] - t[0]) / (t.size - 1)
    if off.any():
        i = _first(off) + 1
        raise _err(
            path,
            f"time column {name!r} is not evenly sampled: the step before "
            f"{table.row_label(i)} is {float(d[i - 1]):.9g} s but the nominal step is {dt:.9g} s; "
            f"resample the data, or give [data].sample_rate if the time stamps "
            f"are only rounded",
        )
    return dt


def load_data(
    path: str | Path,
    columns: list[str],
    time_column: str | None = "time",
    sample_rate: float | None = None,
    missing: str = "error",
) -> Dataset:
    """Read the sensor ``columns`` (and truth columns if present) from a data file.

    With ``sample_rate`` the time axis is ``arange(T) / sample_rate`` and no
    time column is read; otherwise ``time_column`` must exist and be evenly
    sampled. Vendor files (``.uff``/``.unv``, ``.tdms``) carry each channel's
    time and unit: they go through :func:`latentforce.io.channels.load_channels`
    (channels at several rates on one grid, values in SI by the file's unit
    labels). ``missing="error"`` refuses NaN/inf samples; ``"skip"`` keeps
    them as unobserved (``mask`` False, value NaN). A table format's sensor
    channels are as the file holds them (:func:`read_table` gives their unit
    labels); its time is in seconds and its truth in SI by their labels.
    """
    path = Path(path)
    if path.suffix.lower() in _VENDOR_EXTENSIONS:
        # Time from each channel (time_column and sample_rate do not apply), units to SI.
        from latentforce.io.channels import ChannelSpec, load_channels

        _check_path(path, columns, missing)
        return load_channels([ChannelSpec(c) for c in columns], path, missing=missing)
    return read_table(path, columns, time_column, sample_rate, missing)[0]


def read_table(
    path: str | Path,
    columns: list[str],
    time_column: str | None = "time",
    sample_rate: float | None = None,
    missing: str = "error",
) -> tuple[Dataset, dict[str, str | None]]:
    """:func:`load_data` for a table format (``.csv``, ``.h5``, ``.mat``, ``.nc``), and each of the
    ``columns``' unit label in the file (a netCDF/HDF5 ``units`` attribute; None where none)."""
    path = Path(path)
    _check_path(path, columns, missing)
    table = _open(path)
    try:
        dataset = _load(path, table, list(columns), time_column, sample_rate, missing)
        return dataset, {c: table.unit(c) for c in columns}
    finally:
        table.close()


def _check_path(path: Path, columns: list[str], missing: str) -> None:
    if missing not in ("error", "skip"):
        raise ValueError(f"missing must be 'error' or 'skip', got {missing!r}")
    check_file(path)
    if not columns:
        raise ValueError("load_data needs at least one column")


def check_file(path: Path) -> None:
    """A data file that exists, is a file and is not empty, or the error naming it."""
    if not path.exists():
        raise _err(path, "file not found")
    if not path.is_file():
        raise _err(path, "is not a file")
    if path.stat().st_size == 0:
        raise _err(path, "the file is empty")


def _check_rate_against_time(path: Path, table: _Table, columns: list[str], sample_rate: float, T: int) -> None:
    """A file that has a ``time`` column beside ``[data].sample_rate``: the two must agree (a wrong
    rate silently rescales every frequency of the structure and the force)."""
    if "time" not in table.names or "time" in columns:
        return
    try:  # in seconds, as time_column would read it (decoded dates, a unit label)
        t = _in_unit(path, table, "time", _as_vector(path, "time", table.read("time")), "s", "a time column")
    except (TypeError, ValueError, LatentForceError):  # not a time column we can read: nothing to compare
        return
    steps = np.diff(t)
    if t.size != T or T < 2 or not np.all(np.isfinite(steps)) or not np.all(steps > 0):
        return
    step = float(np.median(steps))
    if abs(step * sample_rate - 1.0) > 0.01:
        raise _err(
            path,
            f"[data].sample_rate = {sample_rate:g} Hz gives a step of {1.0 / sample_rate:.6g} s, but the file's "
            f"column 'time' steps by {step:.6g} s ({1.0 / step:.6g} Hz). Remove sample_rate to use the time "
            'column (time_column = "time"), or correct it.',
        )


def _load(
    path: Path, table: _Table, columns: list[str], time_column: str | None, sample_rate: float | None, missing: str
) -> Dataset:
    available = table.names
    listing = ", ".join(repr(n) for n in available) or "(none)"
    for name in columns:
        if name not in available:
            sep = next((c for c in (";", "\t", "|") if c in available[0]), None) if len(available) == 1 else None
            hint = f" The header holds {sep!r}: CSV fields are separated by commas." if sep else ""
            raise _err(
                path, f"column {name!r} not found{_suggest(name, available)}. Available columns: {listing}.{hint}"
            )

    use_time = sample_rate is None
    if use_time:
        time_column = time_column or "time"
        if time_column not in available:
            raise _err(
                path,
                f"time column {time_column!r} not found{_suggest(time_column, available)}. "
                f"Available columns: {listing}. Give [data].time_column, or "
                f"[data].sample_rate for data without a time column",
            )
    elif not sample_rate > 0:
        raise ValueError(f"sample_rate must be positive, got {sample_rate!r}")

    truth_names = [n for n in available if _TRUTH_PATTERN.match(n) and n not in columns and n != time_column]

    # Read everything and check lengths against the first sensor channel.
    channels = {name: _as_vector(path, name, table.read(name)) for name in columns}
    T = channels[columns[0]].size
    extra = ([time_column] if use_time else []) + truth_names
    raw_time = None
    for name in extra:
        raw = table.read(name)
        raw_time = raw if name == time_column and use_time else raw_time
        channels[name] = _as_vector(path, name, raw)
    for name, arr in channels.items():
        if arr.size != T:
            raise _err(
                path,
                f"column {name!r} has {arr.size} samples but column "
                f"{columns[0]!r} has {T}; all channels must have the same length",
            )
    if T == 0:
        raise _err(path, f"column {columns[0]!r} has no samples")
    if T < 2:
        raise _err(path, f"column {columns[0]!r} has {T} sample; at least 2 are needed")

    if use_time:
        time = _in_unit(path, table, time_column, channels[time_column], "s", "a time column")
        dt = _check_time(path, table, time_column, time, _resolution(raw_time, time))
    else:
        dt = 1.0 / float(sample_rate)
        time = np.arange(T) / float(sample_rate)
        _check_rate_against_time(path, table, columns, sample_rate, T)

    values = np.column_stack([channels[n] for n in columns])
    mask = np.isfinite(values)
    if missing == "error":
        for j, name in enumerate(columns):
            bad = ~mask[:, j]
            if bad.any():
                raise _err(
                    path,
                    f"column {name!r} holds {int(bad.sum())} NaN/inf value(s), the first "
                    f'at {table.row_label(_first(bad))}; set missing = "skip" in [data] '
                    f"to treat them as missing observations.",
                )
    values = np.where(mask, values, np.nan)
    truth, notes = _truth_in_si(path, table, {n: channels[n] for n in truth_names})
    return Dataset(time=time, dt=dt, values=values, mask=mask, columns=list(columns), truth=truth, notes=notes)


def _truth_in_si(path: Path, table: _Table, columns: dict[str, np.ndarray]) -> tuple[dict, tuple[str, ...]]:
    """The truth ``columns`` in SI by their unit labels, and a note for each left out because its label does
    not fit (a variable merely named ``force``, say a load cell's volts: it only scores the estimate, so the
    run goes on without it and says so)."""
    truth, notes = {}, []
    for name, si in truth_units(columns).items():
        try:
            truth[name] = _in_unit(path, table, name, columns[name], si, f"a {name} truth column")
        except LatentForceError:
            notes.append(
                f"data file {str(path)!r}: column {name!r} is read as the truth only to score the estimate, "
                f"and its unit label {table.unit(name)!r} does not fit a {name} (a unit like {si!r}): it was left "
                "out, so coverage and NMSE against it are not reported. Correct its label to score against it."
            )
    return truth, tuple(notes)


def truth_units(columns) -> dict[str, str]:
    """The SI unit label of each truth column among ``columns`` (names as ``simulate`` writes them)."""
    return {n: _TRUTH_SI[m.group(1)] for n in columns if (m := _TRUTH_PATTERN.match(n))}
