r"""Sensor channels from one or several files, at one or several rates, onto one time grid, in SI.

Each sensor's channel is read from its own file (the sensor's ``path``, else
``[data].path``) in its own sample times, then all are put on one time grid
of step :math:`\Delta` (the fastest channel's step, or ``[data].dt``) from
the earliest start :math:`t_0`. Channel :math:`j`, sampled from
:math:`t_{0,j}` every :math:`\Delta_j`, has its sample :math:`i` at grid
index

.. math::
    k_{ij} = o_j + i\, r_j, \qquad o_j = (t_{0,j} - t_0)/\Delta, \quad r_j = \Delta_j/\Delta,

which must be integers: within a relative ``RATE_RTOL`` for :math:`r_j` (UFF
headers keep 6 significant digits of the step) and ``OFFSET_TOL`` steps for
:math:`o_j`; otherwise the channel's samples do not fall on the grid and the
rates cannot share it (an error that names both rates and suggests a
``[data].dt`` both share). A channel is observed (``mask`` True) only at its
own samples, and not where its value is NaN; the Kalman filter and the
particle methods then update on the observed subset of each time step.

Units are resolved per channel (:func:`latentforce.io.units.resolve_unit`)
and the values multiplied to SI; :func:`noise_in_si` converts the sensors'
``noise_std`` (given in the channel's unit) with the same factors.
"""

from __future__ import annotations

from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path
from typing import NamedTuple

import numpy as np

from latentforce.errors import LatentForceError
from latentforce.io.data import Dataset, check_file, read_table
from latentforce.io.units import ChannelUnit, resolve_unit
from latentforce.io.vendor import (
    VENDOR_EXTENSIONS,
    RawChannel,
    Sep005Table,
    open_vendor,
)

__all__ = [
    "OFFSET_TOL",
    "RATE_RTOL",
    "ChannelSpec",
    "channel_units",
    "dataset_from_sep005",
    "load_channels",
    "load_problem_data",
    "noise_in_si",
    "sensor_unit_keys",
    "sensor_unit_scales",
]

#: relative tolerance on a channel's step being a whole multiple of the grid's step
RATE_RTOL = 1e-5
#: tolerance, in grid steps, on a channel's first sample falling on a grid point
OFFSET_TOL = 1e-2


class ChannelSpec(NamedTuple):
    """One sensor channel to read.

    ``column``: its name in the file; ``quantity``: the sensor's (None: read
    off the unit); ``unit``: the sensor's ``unit`` (None: the file's, else
    SI); ``path``: its own file (None: the data path); ``label``: how
    messages name the sensor (e.g. ``"[[sensors]][1]"``).
    """

    column: str
    quantity: str | None = None
    unit: str | None = None
    path: Path | None = None
    label: str | None = None


class _Source(NamedTuple):
    raw: RawChannel
    where: str  # "data file 'x.tdms'" or "SEP005 records"


def _who(spec: ChannelSpec) -> str:
    return f"sensor {spec.label} (column {spec.column!r})" if spec.label else f"column {spec.column!r}"


def _check_missing(spec: ChannelSpec, src: _Source, missing: str) -> None:
    bad = ~np.isfinite(src.raw.values)
    if bad.all():
        raise LatentForceError(
            f"{src.where}: channel {spec.column!r} holds no finite value (all {bad.size} samples NaN/inf), so "
            "it observes nothing; fix the file or remove this sensor from the config."
        )
    if missing == "error" and bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise LatentForceError(
            f"{src.where}: channel {spec.column!r} holds {int(bad.sum())} NaN/inf value(s), the first at sample "
            f'{i} (t = {src.raw.t0 + i * src.raw.dt:.6g} s); set missing = "skip" in [data] to treat them '
            "as missing observations."
        )


def _read_sources(
    specs: Sequence[ChannelSpec], path: Path | None, time_column: str | None, sample_rate: float | None, missing: str
):
    """Each spec's channel as it was sampled, plus the truth columns of table-format files (and the notes of
    reading them, :attr:`~latentforce.io.data.Dataset.notes`)."""
    by_file: dict[Path, list[int]] = {}
    for i, spec in enumerate(specs):
        file = spec.path if spec.path is not None else path
        if file is None:
            raise LatentForceError(
                f"{_who(spec)}: no data file: give [data].path (or --data FILE), or a path key in this sensor's table."
            )
        by_file.setdefault(Path(file), []).append(i)
    sources: list[_Source | None] = [None] * len(specs)
    truths: list[tuple[np.ndarray, dict, tuple[str, ...]]] = []  # with each file's notes (Dataset.notes)
    for file, idx in by_file.items():
        where = f"data file {str(file)!r}"
        if file.suffix.lower() in VENDOR_EXTENSIONS:
            check_file(file)
            table = open_vendor(file)
            for i in idx:
                sources[i] = _Source(table.channel(specs[i].column), where)
                _check_missing(specs[i], sources[i], missing)
            continue
        ds, labels = read_table(
            file, [specs[i].column for i in idx], time_column=time_column, sample_rate=sample_rate, missing=missing
        )
        for k, i in enumerate(idx):
            raw = RawChannel(
                values=ds.values[:, k],
                t0=float(ds.time[0]),
                dt=float(ds.dt),
                unit=labels[specs[i].column],
                time=np.asarray(ds.time),
            )
            sources[i] = _Source(raw, where)
            _check_missing(specs[i], sources[i], missing)
        if ds.truth or ds.notes:
            truths.append((np.asarray(ds.time), ds.truth, ds.notes))
    return sources, truths


def _starts(sources: list[_Source]) -> np.ndarray:
    """First-sample times in seconds, aligned on the files' absolute starts where all give one."""
    t0 = np.array([s.raw.t0 for s in sources], dtype=np.float64)
    starts = [s.raw.start for s in sources]
    if all(s is not None for s in starts):
        origin = min(starts)
        t0 = t0 + np.array([(s - origin) / np.timedelta64(1, "s") for s in starts], dtype=np.float64)
    return t0


def _hz(dt: float) -> str:
    return f"{1.0 / dt:.6g} Hz (step {dt:.6g} s)"


def _grid(specs: Sequence[ChannelSpec], sources: list[_Source], dt: float | None):
    """``(t_origin, step, T, index)``: the common grid and each channel's grid indices."""
    t0 = _starts(sources)
    steps = np.array([s.raw.dt for s in sources])
    n = np.array([s.raw.values.size for s in sources])
    ends = t0 + (n - 1) * steps
    late, early = int(np.argmax(t0)), int(np.argmin(ends))
    # Intervals overlap pairwise exactly when the latest start is before the earliest end.
    if t0[late] > ends[early] + OFFSET_TOL * steps.min():
        a, b = specs[early], specs[late]
        raise LatentForceError(
            f"the time spans of {_who(a)} ({sources[early].where}: {t0[early]:.6g} s to {ends[early]:.6g} s) and "
            f"{_who(b)} ({sources[late].where}: {t0[late]:.6g} s to {ends[late]:.6g} s) do not overlap, so no "
            "time has both; check the files' start times (UFF abscissa minimum, TDMS wf_start_offset and "
            "wf_start_time, SEP005 start_timestamp)."
        )
    fastest = int(np.argmin(steps))
    step = float(dt) if dt is not None else float(steps[fastest])
    grid_name = f"[data].dt = {step:.6g} s" if dt is not None else f"the fastest channel's, {_who(specs[fastest])}"
    origin = float(t0.min())
    index = []
    for j, (spec, src) in enumerate(zip(specs, sources)):
        ratio = steps[j] / step
        r = round(ratio)
        offset = (t0[j] - origin) / step
        o = round(offset)
        if r < 1 or abs(ratio - r) > RATE_RTOL * ratio:
            common = Fraction(ratio).limit_denominator(1000)
            hint = (
                f"give [data].dt = {step / common.denominator:.9g} (a step both rates share) or resample"
                if abs(float(common) - ratio) <= RATE_RTOL * ratio
                else "resample the data"
            )
            raise LatentForceError(
                f"{_who(spec)} ({src.where}) is sampled at {_hz(steps[j])} and cannot be put on the common "
                f"time grid of {_hz(step)} ({grid_name}): its sample times do not fall on the grid (the "
                f"ratio of the steps is {ratio:.6g}, not a whole number); {hint}."
            )
        if abs(offset - o) > OFFSET_TOL:
            raise LatentForceError(
                f"{_who(spec)} ({src.where}) starts at {t0[j]:.9g} s, between two points of the common time "
                f"grid of {_hz(step)} ({grid_name}) that starts at {origin:.9g} s ({offset - o:+.3g} steps "
                "off); shift or resample the channel so its samples fall on the grid."
            )
        index.append(o + r * np.arange(src.raw.values.size))
    T = int(max(int(k[-1]) for k in index)) + 1
    return origin, step, T, index


def _assemble(
    specs: Sequence[ChannelSpec],
    sources: list[_Source],
    dt: float | None,
    truths: list[tuple[np.ndarray, dict, tuple[str, ...]]],
) -> Dataset:
    origin, step, T, index = _grid(specs, sources, dt)
    time = None
    for src, k in zip(sources, index):
        # A channel that spans the whole grid at its full rate lends it its own time stamps
        # (a CSV time column: the data set then equals load_data's bit for bit).
        if src.raw.time is not None and k.size == T and k[0] == 0 and (T < 2 or k[1] == 1):
            time = np.asarray(src.raw.time, dtype=np.float64)
            break
    if time is None:
        time = origin + step * np.arange(T)
    values = np.full((T, len(specs)), np.nan)
    units: dict[str, ChannelUnit] = {}
    for j, (spec, src, k) in enumerate(zip(specs, sources, index)):
        unit = resolve_unit(spec.quantity, spec.unit, src.raw.unit, who=_who(spec), where=src.where)
        units[spec.column] = unit
        values[k, j] = src.raw.values * unit.scale if unit.scale != 1.0 else src.raw.values
    mask = np.isfinite(values)
    values = np.where(mask, values, np.nan)
    truth: dict[str, np.ndarray] = {}
    for t, columns, _ in truths:
        if t.size == T and np.allclose(t, time, rtol=0.0, atol=OFFSET_TOL * step):
            truth.update(columns)
    notes = tuple(note for _, _, file_notes in truths for note in file_notes)
    columns = [s.column for s in specs]
    return Dataset(time=time, dt=step, values=values, mask=mask, columns=columns, truth=truth, units=units, notes=notes)


def load_channels(
    specs: Sequence[ChannelSpec],
    path: str | Path | None = None,
    *,
    time_column: str | None = "time",
    sample_rate: float | None = None,
    dt: float | None = None,
    missing: str = "error",
) -> Dataset:
    """Read sensor channels (each from ``spec.path`` or ``path``) onto one time grid, in SI.

    Table formats (``.csv``, ``.h5``, ``.mat``, ``.nc``) take their time from
    ``time_column`` or ``sample_rate`` as in :func:`~latentforce.io.data.load_data`;
    vendor formats (``.uff``/``.unv``, ``.tdms``) from each channel. ``dt``:
    the grid's step (default: the fastest channel's). ``missing``: as in
    ``load_data``.
    """
    if missing not in ("error", "skip"):
        raise ValueError(f"missing must be 'error' or 'skip', got {missing!r}")
    if not specs:
        raise ValueError("load_channels needs at least one channel")
    specs = [s._replace(path=None if s.path is None else Path(s.path)) for s in specs]
    sources, truths = _read_sources(specs, None if path is None else Path(path), time_column, sample_rate, missing)
    return _assemble(specs, sources, dt, truths)


def dataset_from_sep005(
    records,
    columns: Sequence[str] | None = None,
    *,
    problem=None,
    quantities: Sequence[str | None] | None = None,
    units: Sequence[str | None] | None = None,
    dt: float | None = None,
    missing: str | None = None,
) -> Dataset:
    """A :class:`~latentforce.io.data.Dataset` from SEP005 channel dicts (as SDyPy readers return them).

    ``columns`` are record names. With ``problem`` (a
    :class:`~latentforce.io.config.Problem`), the columns, quantities, units
    and ``[data].dt`` / ``missing`` default to its sensors' and ``[data]``'s;
    otherwise ``quantities`` and ``units`` (one per column, None allowed)
    default to None (read the unit off the record's ``unit_str``, the quantity
    off the unit). Pass the result with the problem to
    :func:`latentforce.estimate.run`.
    """
    if problem is not None:
        settings = problem.data
        columns = list(problem.columns) if columns is None else list(columns)
        sensors = {s.name: s for s in problem.model.sensors}
        if quantities is None:
            quantities = [sensors[c].quantity if c in sensors else None for c in columns]
        if units is None:
            given = dict(zip(problem.columns, getattr(settings, "units", ()) or ()))
            units = [given.get(c) for c in columns]
        dt = getattr(settings, "dt", None) if dt is None else dt
        missing = settings.missing if missing is None else missing
    if not columns:
        raise ValueError("dataset_from_sep005 needs the record names to read (columns) or a problem")
    missing = "error" if missing is None else missing
    if missing not in ("error", "skip"):
        raise ValueError(f"missing must be 'error' or 'skip', got {missing!r}")
    columns = list(columns)
    quantities = list(quantities) if quantities is not None else [None] * len(columns)
    units = list(units) if units is not None else [None] * len(columns)
    if not len(quantities) == len(units) == len(columns):
        raise ValueError("quantities and units need one entry per column")
    table = Sep005Table(records)
    specs = [ChannelSpec(c, q, u) for c, q, u in zip(columns, quantities, units)]
    sources = []
    for spec in specs:
        sources.append(_Source(table.channel(spec.column), "SEP005 records"))
        _check_missing(spec, sources[-1], missing)
    return _assemble(specs, sources, dt, [])


def load_problem_data(problem) -> Dataset:
    """The data set of a :class:`~latentforce.io.config.Problem`: its sensors' channels, from
    ``[data].path`` (or ``--data``) and the sensors' own ``path`` keys, on one grid, in SI."""
    settings = problem.data
    units = sensor_unit_keys(problem)
    paths = tuple(getattr(settings, "sensor_paths", ()) or ()) or (None,) * len(problem.columns)
    if settings.path is None and any(p is None for p in paths):
        from latentforce.io.config import data_path

        data_path(problem)  # the config's "no data path" message
    sensors = {s.name: s for s in problem.model.sensors}
    specs = [
        ChannelSpec(
            column=c, quantity=sensors[c].quantity if c in sensors else None, unit=u, path=p, label=f"[[sensors]][{i}]"
        )
        for i, (c, u, p) in enumerate(zip(problem.columns, units, paths))
    ]
    return load_channels(
        specs,
        settings.path,
        time_column=settings.time_column,
        sample_rate=settings.sample_rate,
        dt=getattr(settings, "dt", None),
        missing=settings.missing,
    )


def noise_in_si(problem, dataset: Dataset):
    """The problem with each sensor's ``noise_std`` converted from its channel's unit to SI
    (an inferred one keeps its unit and gets the factor as the sensor's ``noise_scale``).

    ``dataset.units[column].scale`` (SI per channel unit) multiplies the
    values when they are read; the noise standard deviation, given in the same
    unit, takes the same factor. Unchanged when every factor is 1.
    """
    units = getattr(dataset, "units", None) or {}
    scales = [units[s.name].scale if s.name in units else 1.0 for s in problem.model.sensors]
    if all(sc == 1.0 for sc in scales):
        return problem
    from latentforce.models import LatentForceModel

    model = problem.model
    # an inferred noise stays a parameter in the channel's unit: the model scales it (noise_scale)
    sensors = [
        s._replace(
            noise_std=float(s.noise_std) * sc, noise_scale=sc if s.noise_param in problem.free else s.noise_scale
        )
        for s, sc in zip(model.sensors, scales)
    ]
    return problem._replace(model=LatentForceModel(model.system, model.kernel, sensors))


def channel_units(dataset: Dataset) -> dict[str, dict]:
    """The units table of the result files: column -> ``unit`` (SI, what the data now carry),
    ``original`` (what they were given in), ``scale`` (SI per original unit) and ``source``
    (``"sensor"``, ``"file"`` or ``"assumed"``), and ``file_label`` where the sensor's unit overrode a
    file label of another scale. Empty when the data set resolved no units."""
    units = getattr(dataset, "units", None) or {}
    return {
        c: {"unit": u.si, "original": u.unit, "scale": u.scale, "source": u.source}
        | ({"file_label": u.file_label} if u.file_label else {})
        for c, u in units.items()
    }


def sensor_unit_keys(problem) -> tuple[str | None, ...]:
    """Each sensor's ``unit`` key (None where none is given), in sensor order."""
    return tuple(getattr(problem.data, "units", ()) or ()) or (None,) * len(problem.model.sensors)


def sensor_unit_scales(problem) -> list[float]:
    """SI per unit of each sensor's ``unit`` key (1.0 where none is given), in sensor order."""
    return [
        1.0 if u is None else resolve_unit(s.quantity, u, None, who=f"sensor {s.name!r}", where="").scale
        for s, u in zip(problem.model.sensors, sensor_unit_keys(problem))
    ]
