"""Measurement files from acquisition software, read by the libraries made for them.

- UFF 58 / 58b (``.uff``, ``.unv``), read by :mod:`pyuff`: one time record
  per channel, named by its ID line 1 (``id1``); time from the record's
  abscissa start and increment; the unit from its ordinate axis units label.
- TDMS (``.tdms``), read by :mod:`nptdms`: channels named
  ``"group/channel"``; time from the waveform properties ``wf_start_offset``
  and ``wf_increment`` (and ``wf_start_time``, the absolute start); the unit
  from ``unit_string``.
- SEP005 (the SDyPy convention for time series in Python): a list of dicts
  with ``name``, ``data``, ``unit_str`` and ``fs`` or ``time`` (optionally
  ``start_timestamp``, ISO 8601), as the SDyPy readers return them.

Each reader gives :class:`RawChannel` s: a channel's own samples, start,
step and unit label, before any resampling or unit conversion
(:mod:`latentforce.io.channels` does both). A file the library cannot read,
or one that is cut short, is a one-paragraph error naming the file.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import NamedTuple

import numpy as np

from latentforce.errors import LatentForceError

__all__ = ["VENDOR_EXTENSIONS", "RawChannel", "Sep005Table", "TdmsTable", "UffTable", "open_vendor"]

VENDOR_EXTENSIONS = (".uff", ".unv", ".tdms")
# UFF function types that are time records: 0 "general or unknown", 1 "time response".
_UFF_TIME_TYPES = (0, 1)
_UFF_TYPE_NAMES = {
    2: "auto spectrum",
    3: "cross spectrum",
    4: "frequency response function",
    5: "transmissibility",
    6: "coherence",
    7: "auto correlation",
    8: "cross correlation",
    9: "power spectral density",
    10: "energy spectral density",
    11: "probability density function",
    12: "spectrum",
    13: "cumulative frequency distribution",
    14: "peaks valley",
    15: "stress/cycles",
    16: "strain/cycles",
    17: "orbit",
    18: "mode indicator function",
    19: "force pattern",
    20: "partial power",
    21: "partial coherence",
    22: "eigenvalue",
    23: "eigenvector",
    24: "shock response spectrum",
    25: "finite impulse response filter",
    26: "multiple coherence",
    27: "order function",
}
# Time stamps stored as numbers (an uneven UFF abscissa, a SEP005 time vector) must lie this
# close to an even grid, in steps: ASCII UFF keeps 6 significant digits of each time stamp.
_EVEN_TOL = 1e-3


class RawChannel(NamedTuple):
    """One channel as its file holds it: ``values[i]`` at time ``t0 + i * dt`` seconds.

    ``start`` is the absolute time of ``t = 0`` where the file gives one
    (TDMS ``wf_start_time``, SEP005 ``start_timestamp``); channels of
    different files are aligned on it. ``time``: explicit time stamps where
    the file held a time column (``t0 + i * dt`` up to the file's rounding).
    """

    values: np.ndarray
    t0: float
    dt: float
    unit: str | None
    start: np.datetime64 | None = None
    time: np.ndarray | None = None


def _suggest(name: str, names: list[str]) -> str:
    from latentforce.io.data import _suggest as suggest

    return suggest(name, names)


def _listing(names: list[str]) -> str:
    return ", ".join(repr(n) for n in names) or "(none)"


def _numeric(values, fail, what: str) -> np.ndarray:
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise fail(f"{what} is not a 1-D series (shape {arr.shape})")
    if np.iscomplexobj(arr):
        raise fail(f"{what} holds complex numbers (a spectrum?), not a time series")
    if arr.dtype.kind not in "biuf":
        raise fail(f"{what} holds non-numeric data (type {arr.dtype})")
    if arr.size < 2:
        raise fail(f"{what} has {arr.size} sample(s); at least 2 are needed")
    return arr.astype(np.float64)


def _even(x: np.ndarray, fail, what: str) -> tuple[float, float]:
    """``(t0, dt)`` of time stamps that must be evenly spaced (within ``_EVEN_TOL`` steps)."""
    if not np.all(np.isfinite(x)):
        raise fail(f"the time stamps of {what} hold NaN/inf")
    n = x.size
    dt = float(x[-1] - x[0]) / (n - 1)
    if not dt > 0:
        raise fail(f"the time stamps of {what} do not increase")
    off = np.abs(x - (x[0] + dt * np.arange(n)))
    if off.max() > _EVEN_TOL * dt:
        i = int(np.argmax(off))
        raise fail(
            f"{what} is not evenly sampled: sample {i} is at {x[i]!r} s, {off[i] / dt:.3g} steps off "
            f"the even grid of step {dt!r} s from {x[0]!r} s; resample the data"
        )
    return float(x[0]), dt


def _datetime64(value) -> np.datetime64 | None:
    """An absolute time as naive UTC ``datetime64[ns]`` (None stays None)."""
    if value is None:
        return None
    if isinstance(value, str):
        value = datetime.fromisoformat(value)
    if isinstance(value, datetime) and value.tzinfo is not None:
        value = value.astimezone(UTC).replace(tzinfo=None)
    return np.datetime64(value, "ns")


# ----- UFF 58 / 58b ---------------------------------------------------------------
class UffTable:
    """The time records (UFF 58/58b) of a ``.uff``/``.unv`` file, by ID line 1."""

    def __init__(self, path: Path):
        import pyuff

        self.path = path
        self._fail = lambda message: LatentForceError(f"data file {str(path)!r}: {message}")
        # Every UFF data set is closed by a "    -1" line: a file cut short is not. pyuff
        # pairs the delimiters and silently drops an unclosed last record (pyuff 2.5.8).
        with open(path, "rb") as fh:
            fh.seek(max(0, path.stat().st_size - 256))
            tail = fh.read()
        if not tail.rstrip().endswith(b"-1"):
            raise self._fail(
                'is cut short or corrupt: a UFF file ends with a record\'s closing "    -1" '
                "line, and this one does not (an interrupted export or copy?)"
            )
        try:
            self._uff = pyuff.UFF(str(path))
            types = [int(t) for t in self._uff.get_set_types()]
            self._index = [i for i, t in enumerate(types) if t == 58]
            heads = self._uff.read_sets(self._index, header_only=True) if self._index else []
        except Exception as exc:  # noqa: BLE001 - pyuff raises bare Exceptions on malformed files
            raise self._fail(f"is not a readable UFF file (pyuff: {exc})") from None
        if not self._index:
            found = sorted(set(types))
            raise self._fail(
                "holds no UFF 58/58b record (function at a nodal DOF, the time-record data "
                "set)"
                + (
                    f"; its data sets are of type(s) {found}"
                    if found
                    else "; it holds no UFF data set at all (not a UFF file?)"
                )
            )
        self._heads = [heads] if isinstance(heads, dict) else list(heads)
        self.names = [h["id1"] for h in self._heads if h.get("func_type") in _UFF_TIME_TYPES]

    def channel(self, name: str) -> RawChannel:
        hits = [k for k, h in enumerate(self._heads) if h["id1"] == name]
        if not hits:
            raise self._fail(
                f"no UFF 58 time record has ID line 1 {name!r}{_suggest(name, self.names)}. "
                f"Available records (their ID line 1): {_listing(self.names)}."
            )
        if len(hits) > 1:
            raise self._fail(
                f"{len(hits)} UFF 58 records have ID line 1 {name!r} (data sets "
                f"{', '.join(str(self._index[k]) for k in hits)}); the channel is ambiguous"
            )
        head = self._heads[hits[0]]
        kind = head.get("func_type")
        if kind not in _UFF_TIME_TYPES:
            raise self._fail(
                f"record {name!r} is a {_UFF_TYPE_NAMES.get(kind, f'type {kind}')} (UFF 58 "
                f"function type {kind}), not a time record (function type 1)"
            )
        what = f"record {name!r}"
        try:
            record = self._uff.read_sets(self._index[hits[0]])
        except Exception as exc:  # noqa: BLE001 - pyuff raises bare Exceptions on malformed records
            raise self._fail(f"{what} cannot be read (pyuff: {exc}); the file is corrupt") from None
        data = np.asarray(record["data"])
        expected = int(record.get("num_pts", data.size))
        if data.size != expected:
            raise self._fail(
                f"{what} holds {data.size} values but its header announces {expected}; the file is cut short or corrupt"
            )
        values = _numeric(data, self._fail, what)
        unit = str(record.get("ordinate_axis_units_lab", "")).strip() or None
        if int(record.get("abscissa_spacing", 1)) == 1:
            t0, dt = float(record["abscissa_min"]), float(record["abscissa_inc"])
            if not (np.isfinite(t0) and np.isfinite(dt) and dt > 0):
                raise self._fail(
                    f"{what} has abscissa start {t0!r} and increment {dt!r}; the increment "
                    f"(the sample step) must be positive"
                )
            return RawChannel(values=values, t0=t0, dt=dt, unit=unit)
        x = np.asarray(record["x"], dtype=np.float64)
        # ASCII UFF keeps 6 significant digits of each abscissa value: t0 + i dt is the better time.
        t0, dt = _even(x, self._fail, what)
        return RawChannel(values=values, t0=t0, dt=dt, unit=unit)


# ----- TDMS ----------------------------------------------------------------------
class _Collect(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


class TdmsTable:
    """The channels of a ``.tdms`` file, as ``"group/channel"``."""

    def __init__(self, path: Path):
        from nptdms import TdmsFile

        self.path = path
        self._fail = lambda message: LatentForceError(f"data file {str(path)!r}: {message}")
        # npTDMS recovers what it can from a segment cut short (a LabVIEW crash) and says so
        # only in a log warning (npTDMS 1.13): we listen, and refuse such a file.
        # Its own console handler would print them too, before our message: hushed meanwhile.
        handler = _Collect()
        logger = logging.getLogger("nptdms")
        console = getattr(getattr(sys.modules.get("nptdms.log"), "log_manager", None), "console_handler", None)
        level = console.level if console is not None else None
        logger.addHandler(handler)
        if console is not None:
            console.setLevel(logging.CRITICAL)
        try:
            tdms = TdmsFile.read(path)
        except Exception as exc:  # noqa: BLE001 - struct, value and EOF errors from the binary reader
            raise self._fail(f"is not a readable TDMS file (npTDMS: {exc})") from None
        finally:
            logger.removeHandler(handler)
            if console is not None:
                console.setLevel(level)
        if handler.messages:
            raise self._fail(
                f"is cut short or corrupt (npTDMS: {handler.messages[0]}); the last "
                "segment is incomplete (an interrupted acquisition or copy?)"
            )
        self._channels = {f"{g.name}/{c.name}": c for g in tdms.groups() for c in g.channels()}
        self.names = list(self._channels)

    def channel(self, name: str) -> RawChannel:
        if name not in self._channels:
            raise self._fail(
                f"channel {name!r} not found{_suggest(name, self.names)}. Available channels "
                f'("group/channel"): {_listing(self.names)}.'
            )
        ch = self._channels[name]
        what = f"channel {name!r}"
        props = ch.properties
        if "wf_increment" not in props:
            raise self._fail(
                f"{what} has no waveform timing (the wf_increment property, the sample step "
                "in seconds); save it as a waveform channel"
            )
        dt = float(props["wf_increment"])
        t0 = float(props.get("wf_start_offset", 0.0))
        if not (np.isfinite(t0) and np.isfinite(dt) and dt > 0):
            raise self._fail(
                f"{what} has wf_start_offset {t0!r} and wf_increment {dt!r}; the increment "
                "(the sample step) must be positive"
            )
        values = _numeric(ch[:], self._fail, what)
        unit = props.get("unit_string")
        return RawChannel(
            values=values,
            t0=t0,
            dt=dt,
            unit=None if unit is None else str(unit),
            start=_datetime64(props.get("wf_start_time")),
        )


# ----- SEP005 ------------------------------------------------------------------------
class Sep005Table:
    """A list of SEP005 channel dicts, by ``name``."""

    def __init__(self, records):
        self._fail = lambda message: LatentForceError(f"SEP005 records: {message}")
        if isinstance(records, Mapping):
            records = [records]
        if not isinstance(records, (list, tuple)):
            raise self._fail(f"expected a list of SEP005 channel dicts, got {type(records).__name__}")
        for i, rec in enumerate(records):
            if not isinstance(rec, Mapping):
                raise self._fail(f"record {i} is a {type(rec).__name__}, not a dict")
            for key in ("name", "data"):
                if key not in rec:
                    raise self._fail(
                        f"record {i} has no {key!r} key (SEP005 channels need name, data, unit_str and fs or time)"
                    )
            if "fs" not in rec and "time" not in rec:
                raise self._fail(
                    f"record {i} ({rec['name']!r}) has neither 'fs' (samples per second) nor "
                    "'time' (the time vector): its time axis is unknown"
                )
        self._records = list(records)
        self.names = [str(r["name"]) for r in self._records]

    def channel(self, name: str) -> RawChannel:
        hits = [i for i, n in enumerate(self.names) if n == name]
        if not hits:
            raise self._fail(
                f"no record is named {name!r}{_suggest(name, self.names)}. Available records: {_listing(self.names)}."
            )
        if len(hits) > 1:
            raise self._fail(f"records {', '.join(map(str, hits))} are all named {name!r}; the channel is ambiguous")
        rec = self._records[hits[0]]
        what = f"record {hits[0]} ({name!r})"
        values = _numeric(rec["data"], self._fail, what)
        if "fs" in rec:
            fs = rec["fs"]
            if isinstance(fs, bool) or not isinstance(fs, (int, float, np.number)) or not (np.isfinite(fs) and fs > 0):
                raise self._fail(f"{what} has fs = {fs!r}; it must be a positive number (samples per second)")
            t0, dt, time = 0.0, 1.0 / float(fs), None
        else:
            time = _numeric(rec["time"], self._fail, f"the time vector of {what}")
            if time.size != values.size:
                raise self._fail(f"{what} has {values.size} data values but {time.size} time values")
            t0, dt = _even(time, self._fail, what)
        unit = rec.get("unit_str", rec.get("unit"))
        try:
            start = _datetime64(rec.get("start_timestamp"))
        except (TypeError, ValueError) as exc:
            raise self._fail(
                f"{what} has start_timestamp {rec.get('start_timestamp')!r}, which is not an ISO 8601 time ({exc})"
            ) from None
        return RawChannel(values=values, t0=t0, dt=dt, unit=None if unit is None else str(unit), start=start, time=time)


def open_vendor(path: Path) -> UffTable | TdmsTable:
    """The reader for a vendor file, chosen by its extension (one of ``VENDOR_EXTENSIONS``)."""
    ext = path.suffix.lower()
    try:
        if ext in (".uff", ".unv"):
            return UffTable(path)
        if ext == ".tdms":
            return TdmsTable(path)
    except OSError as exc:
        raise LatentForceError(f"data file {str(path)!r}: cannot be read ({exc})") from None
    raise ValueError(f"not a vendor file extension: {ext!r}")
