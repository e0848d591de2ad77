r"""Benchmark: a monitoring campaign through ``latentforce batch`` (the first record against the later ones).

The question (issue 23, "Campaigns"): what does each record of a campaign cost
when the first one compiles the programs and the later ones reuse them (in the
same worker process, and through the persistent compile cache across
processes)? And does the trend figure show a stiffness drop?

The case: an SDOF structure monitored hourly, eight records of 40 s at 50 Hz
(2 001 samples) named ``deck_2026-11-26THH-00.csv``; m = 1 (fixed),
c = 0.5, k = 158 N/m (2.0 Hz) for the first five hours, then k = 140
(an 11 % drop); a Matérn-3/2 force (variance 1, lengthscale 0.5 s); one
accelerometer (noise sd 0.05). Each record is drawn by ``latentforce
simulate`` (seed = the hour). Inferred, as in ``linear_long.py``: c ~
logN(log 0.5, 1), k ~ logN(log 150, 0.5), force variance ~ logN(0, 2),
lengthscale ~ logN(0, 1); ``kalman-mcmc`` at its defaults (iterations =
"auto": until converged, 4 chains).

Runs, each ``latentforce batch`` in a fresh process (the CLI, as a user runs it):

1. ``--workers 1``, an empty compile cache: record 1 compiles, the later ones
   reuse the worker's programs;
2. ``--workers 2``, an empty compile cache: both workers compile at once;
3. ``--workers 2``, the cache that run 2 filled, into a new folder: every
   worker's first record loads the programs from the cache;
4. run 3 again: every record skipped.

The per-record wall time is ``batch.csv``'s ``wall_time_s`` (reading,
inference and writing on the worker); the campaign's wall time includes
starting the cluster. Run 2's trend figure is copied to
``docs/images/batch_trend.png``.

Usage::

    PYTHONPATH=src python benchmarks/batch_campaign.py            # all runs, 8 records
    PYTHONPATH=src python benchmarks/batch_campaign.py --quick    # runs 3-4 skipped, 4 records
"""

from __future__ import annotations

import argparse
import csv
import datetime
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = ROOT / "benchmarks" / "results"
FIGURE = ROOT / "docs" / "images" / "batch_trend.png"
RATE, DURATION = 50.0, 40.0
K_BEFORE, K_AFTER, DROP_HOUR = 158.0, 140.0, 5

TRUTH = """
[data]
sample_rate = 50.0

[system]
type = "linear"
m = 1.0
c = 0.5
k = {k}

[force]
kernel = "matern32"
variance = 1.0
lengthscale = 0.5

[[sensors]]
column = "acc"
quantity = "acceleration"
dof = 0
noise_std = 0.05

[inference]
method = "kalman"
"""

CAMPAIGN = """
[data]
sample_rate = 50.0

[system]
type = "linear"
m = 1.0
c = { prior = "lognormal", mu = -0.6931, sigma = 1.0, init = 0.8 }
k = { prior = "lognormal", mu = 5.0106, sigma = 0.5, init = 120.0 }

[force]
kernel = "matern32"
variance = { prior = "lognormal", mu = 0.0, sigma = 2.0, init = 2.0 }
lengthscale = { prior = "lognormal", mu = 0.0, sigma = 1.0, init = 0.3 }

[[sensors]]
column = "acc"
quantity = "acceleration"
dof = 0
noise_std = 0.05

[inference]
method = "kalman-mcmc"
"""


def cli(*args: str, cache: Path | None = None) -> tuple[float, int, str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    if cache is not None:
        env["LATENTFORCE_CACHE_DIR"] = str(cache)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "latentforce.cli", *args], env=env, capture_output=True, text=True)
    return time.perf_counter() - t0, proc.returncode, proc.stdout + proc.stderr


def load() -> str:
    return ", ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="4 records, runs 1 and 2 only")
    args = parser.parse_args()
    hours = range(4 if args.quick else 8)
    work = Path(tempfile.mkdtemp(prefix="lf-campaign-"))
    records = work / "records"
    records.mkdir()
    for h in hours:
        k = K_BEFORE if h < DROP_HOUR else K_AFTER
        (work / "truth.toml").write_text(TRUTH.format(k=k))
        _, code, text = cli(
            "simulate",
            str(work / "truth.toml"),
            "--out",
            str(records / f"deck_2026-11-26T{h:02d}-00.csv"),
            "--duration",
            str(DURATION),
            "--sample-rate",
            str(RATE),
            "--seed",
            str(h),
        )
        assert code == 0, text
    (work / "campaign.toml").write_text(CAMPAIGN)
    started = f"{datetime.datetime.now().isoformat(timespec='seconds')}, load average {load()}"

    runs = [("1 worker, empty cache", "1", "c1", "camp1"), ("2 workers, empty cache", "2", "c2", "camp2")]
    if not args.quick:
        runs += [
            ("2 workers, cache of run 2", "2", "c2", "camp3"),
            ("rerun of run 3 (all skipped)", "2", "c2", "camp3"),
        ]
    table = []
    for label, workers, cache, out in runs:
        wall, code, text = cli(
            "batch",
            str(work / "campaign.toml"),
            str(records / "*.csv"),
            "--out",
            str(work / out),
            "--workers",
            workers,
            cache=work / cache,
        )
        assert code == 0, text
        with open(work / out / "batch.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        table.append((label, wall, rows))
        print(
            f"{label}: {wall:.1f} s; per record " + ", ".join(f"{float(r['wall_time_s']):.1f}" for r in rows),
            flush=True,
        )
        if out == "camp2":
            shutil.copyfile(work / out / "trend.png", FIGURE)

    lines = [
        f"# A campaign through `latentforce batch`{' (quick)' if args.quick else ''}",
        "",
        f"{len(hours)} hourly SDOF records of {DURATION:g} s at {RATE:g} Hz "
        f"({int(DURATION * RATE) + 1} samples), k = {K_BEFORE:g} N/m until hour {DROP_HOUR - 1}, then "
        f"{K_AFTER:g}; kalman-mcmc at its defaults (until converged, 4 chains). Each run is "
        "`latentforce batch` in a fresh process (benchmarks/batch_campaign.py).",
        f"Start: {started}; end: load average {load()}; {platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}.",
        "",
        "Per-record wall time: `batch.csv`'s `wall_time_s` (reading, inference, writing the result folder "
        "on the worker), in record order. A skipped record shows the time of the run that finished it.",
        "",
        "| run | campaign s | record 1 s | records 2.. s (median, min-max) | converged |",
        "|---|---:|---:|---|---|",
    ]
    for label, wall, rows in table:
        times = [float(r["wall_time_s"]) for r in rows]
        later = sorted(times[1:])
        mid = len(later) // 2
        median = later[mid] if len(later) % 2 else 0.5 * (later[mid - 1] + later[mid])
        statuses = {r["status"] for r in rows}
        lines.append(
            f"| {label} ({'/'.join(sorted(statuses))}) | {wall:.1f} | {times[0]:.1f} | "
            f"{median:.1f} ({later[0]:.1f}-{later[-1]:.1f}) | "
            f"{sum(r['converged'] == 'true' for r in rows)}/{len(rows)} |"
        )
    lines += [
        "",
        "Per record (s): "
        + "; ".join(
            f"{label}: " + ", ".join(f"{float(r['wall_time_s']):.1f}" for r in rows) for label, _, rows in table
        ),
        "",
        "k posterior mean ± sd per record (run 2): "
        + ", ".join(f"{float(r['k_mean']):.1f} ± {float(r['k_sd']):.1f}" for r in table[1][2]),
        "",
    ]
    name = "batch_campaign_quick.md" if args.quick else "batch_campaign.md"
    (RESULTS_DIR / name).write_text("\n".join(lines))
    print("\n".join(lines))
    shutil.rmtree(work)


if __name__ == "__main__":
    main()
