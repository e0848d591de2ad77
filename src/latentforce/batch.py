"""Campaigns: one configuration, many records, on Dask distributed (``latentforce batch``).

Each record (a data file) becomes a result folder ``DIR/NAME`` written by the
path of ``latentforce estimate`` (:func:`latentforce.cli.estimate_into`), run
as one task on a Dask cluster: a :class:`~dask.distributed.LocalCluster` of
single-threaded worker processes by default (JAX wants a process of its
own), or any running scheduler by address, with no change to the code. The
workers read and write the paths the client gives them, so on a cluster the
data, the configuration and ``DIR`` must lie on a shared file system.

Which records run
    Each folder gets ``batch_record.json``: the hash of the configuration
    file's bytes and of the data file's bytes (:func:`record_key`) and a
    ``status``. It is written ``started`` before the run and replaced (a
    temporary file renamed over it, so never half written) by ``done``, with
    the record's row of ``batch.csv``, once the result folder is complete, or
    by ``failed`` with the message. A rerun skips a ``done`` folder of the
    same hash, reruns an unfinished or failed one, and refuses, before any
    work and unless ``--force``, a finished folder of another hash or a
    non-empty folder that ``batch`` did not write (as ``estimate`` refuses
    an existing result folder).

Names and order
    A folder is named after its file's stem; files whose stems clash (in
    different folders, or ``rec.csv`` beside ``rec.h5``) take their name
    with the extension, then with as many parent folders (joined by ``--``)
    as tell them apart. The records are in time order when every file name
    carries a timestamp (:func:`name_timestamp`), otherwise in file order:
    the order of the arguments, each glob's or folder's files sorted by
    name. The time column of a record is no help (it usually starts at 0).

The table and the trend figure are written by :mod:`latentforce.batch_report`.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import importlib.util
import json
import logging
import os
import re
import sys
import time as _time
from collections import Counter
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import numpy as np

from latentforce.errors import LatentForceError

__all__ = [
    "Record",
    "expand_inputs",
    "name_timestamp",
    "folder_names",
    "plan_records",
    "record_key",
    "folder_state",
    "run_record",
    "run_batch",
    "RECORD_FILE",
    "EXIT_SOME_FAILED",
]

#: the file in each record's folder that says which config and data it holds and whether it finished
RECORD_FILE = "batch_record.json"
#: exit code of ``batch`` when some records failed (the others are written all the same)
EXIT_SOME_FAILED = 4
_HASH_CHUNK = 1 << 20
#: seconds to wait for a scheduler given by --scheduler
CONNECT_TIMEOUT_S = 20.0


@dataclass(frozen=True)
class Record:
    """One data file of a campaign."""

    path: Path  # absolute, what the workers read
    shown: str  # the path as the user gave it (or the glob found it), for the table and messages
    folder: str  # the result folder's name under DIR
    timestamp: datetime | None  # from the file name, if any


# ----- which files, in which order, under which names ----------------------------------------


def expand_inputs(patterns: list[str]) -> list[tuple[Path, str]]:
    """``(absolute path, shown path)`` of every data file the arguments name, in file order.

    An argument is a file, a folder (its files with a supported extension,
    sorted by name, not recursive) or a glob pattern (``*``, ``?``, ``[``;
    ``**`` recursive), expanded here so that quoting behaves alike on every
    shell; its matches sorted by name. A file named twice is kept once, at
    its first place. A missing file or a pattern that matches nothing is an
    error (a typo, before any work).
    """
    from latentforce.io.data import SUPPORTED_EXTENSIONS

    found: list[tuple[Path, str]] = []
    seen: set[Path] = set()

    def add(shown: str) -> None:
        path = Path(shown).expanduser().resolve()
        if path not in seen:
            seen.add(path)
            found.append((path, shown))

    for pattern in patterns:
        p = Path(pattern).expanduser()
        if p.is_dir():
            files = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in SUPPORTED_EXTENSIONS)
            if not files:
                raise LatentForceError(
                    f"The folder {pattern!r} holds no data file ({', '.join(SUPPORTED_EXTENSIONS)}); nothing was run."
                )
            for q in files:
                add(str(q))
        elif p.exists():
            add(pattern)
        elif glob.has_magic(pattern):
            matches = sorted(m for m in glob.glob(os.path.expanduser(pattern), recursive=True) if os.path.isfile(m))
            if not matches:
                raise LatentForceError(f"No file matches {pattern!r}; nothing was run.")
            for m in matches:
                add(m)
        else:
            raise LatentForceError(f"The data file {pattern!r} does not exist; nothing was run.")
    if not found:
        raise LatentForceError("No data files given; nothing was run.")
    return found


# 2026-11-26T01-00, 2026-11-26_01:00:30, 2026-11-26 (a day) ...
_STAMP_DASHED = re.compile(r"(?<!\d)(\d{4})-(\d{2})-(\d{2})(?:[T_ ](\d{2})[-:h]?(\d{2})(?:[-:m]?(\d{2}))?)?(?!\d)")
# 20261126_0100, 20261126T010000 (eight digits alone are too often an id to read as a date)
_STAMP_COMPACT = re.compile(r"(?<!\d)(\d{4})(\d{2})(\d{2})[T_-](\d{2})(\d{2})(\d{2})?(?!\d)")


def name_timestamp(name: str) -> datetime | None:
    """The timestamp in a file name, or None.

    Recognised: ``YYYY-MM-DD`` optionally followed by ``T``, ``_`` or a space
    and ``HH-MM[-SS]`` (also ``HH:MM``, ``HHMM``), and ``YYYYMMDD`` followed by
    ``T``, ``_`` or ``-`` and ``HHMM[SS]``. The first valid one counts.
    """
    for pattern in (_STAMP_DASHED, _STAMP_COMPACT):
        for match in pattern.finditer(name):
            parts = [int(g) if g is not None else 0 for g in match.groups()]
            try:
                return datetime(*parts)
            except ValueError:  # 2026-13-45: not a date
                continue
    return None


def folder_names(paths: list[Path]) -> list[str]:
    """A distinct result-folder name per path (module doc): the stem, where it clashes the name
    with its extension, then more parent folders joined by ``--``. Names are compared
    case-insensitively (for file systems that do)."""

    def name(path: Path, level: int) -> str:
        if level == 0:
            return path.stem
        parts = path.parts[-level:] if level <= len(path.parts) - 1 else path.parts[1:]
        return "--".join(parts)

    levels = [0] * len(paths)
    for _ in range(max((len(p.parts) for p in paths), default=1) + 2):
        names = [name(p, lv) for p, lv in zip(paths, levels)]
        counts = Counter(n.casefold() for n in names)
        clashing = [i for i, n in enumerate(names) if counts[n.casefold()] > 1]
        if not clashing:
            return names
        for i in clashing:
            levels[i] += 1
    # distinct paths whose joined parts still agree (names with "--" in them): add a hash
    return [
        n if counts[n.casefold()] == 1 else f"{n}-{hashlib.sha256(str(p).encode()).hexdigest()[:8]}"
        for n, p in zip(names, paths)
    ]


def plan_records(patterns: list[str]) -> tuple[list[Record], str]:
    """The campaign's records in order, and the rule used (``"time"`` or ``"file"``; module doc)."""
    found = expand_inputs(patterns)
    names = folder_names([p for p, _ in found])
    records = [Record(path=p, shown=s, folder=n, timestamp=name_timestamp(p.name)) for (p, s), n in zip(found, names)]
    if all(r.timestamp is not None for r in records):
        order = sorted(range(len(records)), key=lambda i: (records[i].timestamp, i))
        return [records[i] for i in order], "time"
    return records, "file"


# ----- what a folder holds -------------------------------------------------------------------


def _file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(_HASH_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def record_key(config_sha256: str, data_path: Path) -> dict:
    """The identity of a record's result: the config's and the data file's SHA-256, and one key
    over both (``sha256("latentforce-batch-1:" + config + ":" + data)``)."""
    data_sha256 = _file_sha256(data_path)
    key = hashlib.sha256(f"latentforce-batch-1:{config_sha256}:{data_sha256}".encode()).hexdigest()
    return {"key": key, "config_sha256": config_sha256, "data_sha256": data_sha256}


def read_record_file(folder: Path) -> dict | None:
    """``batch_record.json`` of a folder, or None when absent or unreadable."""
    try:
        return json.loads((folder / RECORD_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def folder_state(folder: Path, key: str) -> str:
    """``"new"`` (absent or empty), ``"finished"`` (done, this key), ``"other"`` (done, another
    key), ``"unfinished"`` (started or failed: batch wrote it, nothing finished) or ``"foreign"``
    (not a folder, or non-empty without a readable ``batch_record.json``)."""
    if not folder.exists():
        return "new"
    if not folder.is_dir():
        return "foreign"
    if not any(folder.iterdir()):
        return "new"
    info = read_record_file(folder)
    if not isinstance(info, dict):
        return "foreign"
    if info.get("status") != "done":
        return "unfinished"
    from latentforce.results import RESULT_FILES

    complete = all((folder / f).is_file() for f in RESULT_FILES)
    if info.get("key") == key and complete:
        return "finished"
    return "other" if complete else "unfinished"


def _write_json(path: Path, payload: dict) -> None:
    """Write through a temporary file renamed over ``path``: readers see the old or the new file."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    os.replace(tmp, path)


# ----- one record (a Dask task) --------------------------------------------------------------


def _record_row(out: Path, result) -> dict:
    """The record's row of ``batch.csv``, from the summary.json just written and the posterior
    mean force: ``converged``, ``NAME_mean`` and ``NAME_sd`` per parameter, ``force_rms``
    (``force_J_rms`` per force of several), the root mean square over time of the mean force."""
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    row: dict = {"converged": bool(summary.get("converged", False))}
    for name, stats in (summary.get("parameters") or {}).items():
        row[f"{name}_mean"] = stats.get("mean")
        row[f"{name}_sd"] = stats.get("sd")
    force = np.asarray(result.state_mean.get("force", np.zeros((0, 0))), dtype=float)
    force = force.reshape(force.shape[0], -1) if force.ndim != 2 else force
    for j in range(force.shape[1]):
        rms = float(np.sqrt(np.nanmean(force[:, j] ** 2))) if force.shape[0] else float("nan")
        row["force_rms" if force.shape[1] == 1 else f"force_{j}_rms"] = rms if np.isfinite(rms) else None
    return row


def run_record(config_path: str, data_path: str, folder: str, key: dict, shown: str = "") -> dict:
    """Run one record into ``folder`` (the Dask task; the client has checked the folder).

    Never raises for a failed record: returns its row with ``status`` ``failed`` and the
    message (a :class:`LatentForceError`'s paragraph, or the internal error's type and text).
    The persistent compile cache of the CLI (``LATENTFORCE_CACHE_DIR`` in the *worker's*
    environment) is on, so a record after the first skips compiling.
    """
    import latentforce

    latentforce.enable_x64()  # a worker process: the CLI's setting is not inherited
    from latentforce.cli import _compilation_cache, estimate_into
    from latentforce.io.config import load_config

    t0 = _time.perf_counter()
    out = Path(folder)
    row = {"file": shown or data_path, "folder": out.name}
    marker = {**key, "config": config_path, "data": data_path}
    try:
        out.mkdir(parents=True, exist_ok=True)
        _write_json(out / RECORD_FILE, {**marker, "status": "started"})
        with _compilation_cache():
            problem = load_config(config_path, data_override=data_path)
            # force: the folder holds our marker, and the client decided it may be written
            result = estimate_into(problem, out, force=True)
        row.update(status="done", error="", wall_time_s=_time.perf_counter() - t0, **_record_row(out, result))
    except Exception as err:  # noqa: BLE001 - a record's failure is reported, never raised
        if isinstance(err, LatentForceError):
            message = str(err)
        else:
            message = f"internal error ({type(err).__name__}: {err})"
        row.update(status="failed", error=" ".join(message.split()), wall_time_s=_time.perf_counter() - t0)
    from latentforce import __version__

    finished = datetime.now(timezone.utc).isoformat(timespec="seconds")
    try:
        _write_json(
            out / RECORD_FILE,
            {
                **marker,
                "status": row["status"],
                "error": row["error"],
                "finished": finished,
                "version": __version__,
                "row": row,
            },
        )
    except (OSError, ValueError) as err:
        if row["status"] == "done":  # without its record the folder is not finished: say so
            row.update(status="failed", error=f"the result was written but {out / RECORD_FILE} could not be: {err}")
    return row


# ----- the campaign --------------------------------------------------------------------------


@dataclass
class BatchOutcome:
    """What ``run_batch`` did: the rows in record order, the ordering rule, the files written."""

    rows: list[dict]
    order: str
    table: Path
    trend: Path

    def count(self, status: str) -> int:
        return sum(r["status"] == status for r in self.rows)


def _refusal(out: Path, clashes: dict[str, list[str]]) -> LatentForceError:
    parts = []
    for why, names in clashes.items():
        shown = ", ".join(repr(str(out / n)) for n in names[:5])
        more = f" and {len(names) - 5} more" if len(names) > 5 else ""
        parts.append(f"{shown}{more} ({why})")
    return LatentForceError(
        f"Result folders under {str(out)!r} hold results this batch would replace: {'; '.join(parts)}. "
        "Nothing was run. Pass --force to replace their results (other files in them are kept), or "
        "choose another --out."
    )


@contextlib.contextmanager
def dask_client(scheduler: str | None, workers: int):
    """A Dask client: of the scheduler at ``scheduler``, else of a new LocalCluster of ``workers``
    single-threaded processes (closed on exit)."""
    from dask.distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as err:
            raise LatentForceError(
                f"Cannot reach the Dask scheduler at {scheduler!r} ({err}); nothing was "
                "run. Start one with `dask scheduler` and workers with "
                "`dask worker ADDRESS`, or leave out --scheduler to run here."
            ) from None
        with client:
            yield client
        return
    # ":0": the scheduler's web server (and dashboard, with bokeh) on a free port, so that two
    # campaigns, or a campaign beside a user's own cluster on 8787, start without a warning
    with (
        LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0", silence_logs=logging.ERROR
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def run_batch(
    config: Path,
    patterns: list[str],
    out: Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    force: bool = False,
    echo: Callable[[str], None] = print,
) -> BatchOutcome:
    """Run a campaign (module doc); write ``out/batch.csv`` and ``out/trend.png``.

    ``echo`` gets one line per failed record (``error: FILE: message``) as it fails.
    """
    from latentforce.batch_report import write_table, write_trend
    from latentforce.io.config import load_config

    records, order = plan_records(patterns)
    try:
        config_sha256 = _file_sha256(config)
    except OSError as err:
        raise LatentForceError(f"config file {str(config)!r} cannot be read ({err}).") from None
    # a broken config fails once, here, not once per record
    load_config(config, data_override=str(records[0].path))
    if out.exists() and not out.is_dir():
        raise LatentForceError(f"--out {str(out)!r} is an existing file, not a folder; nothing was run.")
    if workers is not None and workers < 1:
        raise LatentForceError(f"--workers must be at least 1, not {workers}.")
    if workers is not None and scheduler:
        echo("warning: --workers is ignored with --scheduler: the scheduler's workers run the records.")

    rows: dict[str, dict] = {}
    to_run: list[tuple[Record, dict]] = []
    clashes: dict[str, list[str]] = {}
    for rec in records:
        try:
            key = record_key(config_sha256, rec.path)
        except OSError as err:
            rows[rec.folder] = {
                "file": rec.shown,
                "folder": rec.folder,
                "status": "failed",
                "error": f"the data file {rec.shown!r} cannot be read ({err}).",
                "wall_time_s": 0.0,
            }
            continue
        state = folder_state(out / rec.folder, key["key"])
        if state == "finished":
            info = read_record_file(out / rec.folder) or {}
            rows[rec.folder] = {
                **info.get("row", {}),
                "file": rec.shown,
                "folder": rec.folder,
                "status": "skipped",
                "error": "",
            }
            continue
        if state in ("other", "foreign") and not force:
            why = (
                "finished results of another config or data file"
                if state == "other"
                else f"files not written by batch: no {RECORD_FILE}"
            )
            clashes.setdefault(why, []).append(rec.folder)
        to_run.append((rec, key))
    if clashes:
        raise _refusal(out, clashes)
    for rec in records:
        if rows.get(rec.folder, {}).get("status") == "failed":
            echo(f"error: {rec.shown}: {rows[rec.folder]['error']}")

    out.mkdir(parents=True, exist_ok=True)
    if to_run:
        n_workers = workers if workers is not None else max(1, min(os.cpu_count() or 1, len(to_run)))
        rows.update(_run_on_dask(config, out, to_run, scheduler, n_workers, echo))
    ordered = [{**rows[r.folder], "timestamp": r.timestamp.isoformat() if r.timestamp else ""} for r in records]
    table = write_table(out, ordered)
    trend = write_trend(out, ordered, order=order, title=f"{config.name}: {len(records)} records")
    return BatchOutcome(rows=ordered, order=order, table=table, trend=trend)


def _run_on_dask(
    config: Path,
    out: Path,
    to_run: list[tuple[Record, dict]],
    scheduler: str | None,
    workers: int,
    echo: Callable[[str], None],
) -> dict[str, dict]:
    """Submit one task per record, in record order; their rows by folder name, as they finish."""
    from dask.distributed import as_completed
    from tqdm import tqdm

    rows: dict[str, dict] = {}
    bar = tqdm(
        total=len(to_run), desc="batch", unit="record", file=sys.stderr, leave=False, disable=not sys.stderr.isatty()
    )
    say = bar.write if not bar.disable else echo
    with dask_client(scheduler, workers) as client:
        if importlib.util.find_spec("bokeh") is not None:
            say(f"batch: {len(to_run)} record(s) to run; Dask dashboard at {client.dashboard_link}")
        futures = {}
        for rec, key in to_run:
            future = client.submit(
                run_record,
                str(config.resolve()),
                str(rec.path),
                str((out / rec.folder).resolve()),
                key,
                rec.shown,
                pure=False,
            )
            futures[future] = rec
        try:
            for future in as_completed(futures):
                rec = futures[future]
                try:
                    row = future.result()
                except Exception as err:  # noqa: BLE001 - the task itself was lost (a worker died ...)
                    row = {
                        "file": rec.shown,
                        "folder": rec.folder,
                        "status": "failed",
                        "wall_time_s": None,
                        "error": f"the Dask task did not finish ({type(err).__name__}: {err})",
                    }
                rows[rec.folder] = row
                if row["status"] == "failed":
                    say(f"error: {rec.shown}: {row['error']}")
                bar.update(1)
        finally:
            bar.close()
            for future in futures:
                future.cancel()
    return rows
