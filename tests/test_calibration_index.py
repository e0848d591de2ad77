"""The calibration overview (``benchmarks/calibration_index.py``): newest run per study, the
rules applied to the cells, and the committed ``calibration.md`` in step with the result files."""

import importlib.util
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"


def _index():
    spec = importlib.util.spec_from_file_location("calibration_index", BENCH / "calibration_index.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["calibration_index"] = module
    spec.loader.exec_module(module)
    return module


SBC_HEADER = (
    "| case | sampler | T | runs | param | cover 50 % | cover 90 % | SBC χ² p | SBC KS p | ranks | converged "
    "| R-hat (median) | bulk ESS (median) | s/run (first) |\n"
    "|---|---|---:|---:|---|---:|---:|---:|---:|---|---:|---:|---:|---:|\n"
)


def _sbc_file(path, date, runs, chi2_second, converged="1.00"):
    path.write_text(
        f"# Calibration of the samplers (full)\n\n{date}; x86_64, 2 cores\n\n"
        + SBC_HEADER
        + f"| toy | pgas | 65 | {runs} | a | 0.50 ± 0.11 | 0.90 ± 0.07 | 0.500 | 0.400 | `████` | {converged} "
        "| 1.004 | 700 | 10.0 (50.0) |\n"
        f"|  |  |  |  | b | 0.55 ± 0.11 | 0.85 ± 0.07 | **{chi2_second}** | 0.300 | `████` |  | 1.012 | 450 |  |\n",
        encoding="utf-8",
    )


RECORD = "\n".join(
    [
        "# Calibration of the nonlinear methods on Duffing records",
        "",
        "2026-11-20T10:00:00; x86_64, 2 cores",
        "",
        "| case | nonlinear share | method | force ±1/±2/±3 sd % | displacement ±1/±2/±3 sd % | force NMSE % "
        "| converged | max R-hat | min bulk ESS | switch rate | s |",
        "|---|---:|---|---|---|---:|---|---:|---:|---:|---:|",
        "| Matérn-3/2, acc | 60 % | pgas | 70.0 / 96.0 / 99.0 | 90.0 / 99.0 / 100.0 | 1.0 "
        "| yes | 1.005 | 500 | 0.1 | 30 |",
        "| Matérn-5/2, acc | 60 % | pgas | 70.0 / 96.0 / 99.0 | 70.0 / 99.0 / 100.0 | 1.0 "
        "| yes | 1.005 | 500 | 0.1 | 30 |",
        "| Matérn-5/2, acc | 60 % | ekf | 50.0 / 86.0 / 93.0 | 70.0 / 99.0 / 100.0 | 3.0 | yes | – | – | – | 2 |",
        "",
    ]
)


def test_the_newest_run_of_each_study_is_shown_and_the_rules_are_recomputed(tmp_path):
    ci = _index()
    _sbc_file(tmp_path / "calibration_a.md", "2026-11-20T10:00:00", 20, "0.002")
    _sbc_file(tmp_path / "calibration_b.md", "2026-11-22T10:00:00", 40, "0.200", converged="0.90")
    _sbc_file(tmp_path / "calibration_c_quick.md", "2026-11-23T10:00:00", 1, "0.900")  # CI smoke: left out
    (tmp_path / "nonlinear_calibration_x.md").write_text(RECORD, encoding="utf-8")
    text = ci.build(tmp_path, expected=[("toy", "pgas"), ("missing", "pgas")])

    toy = next(line for line in text.splitlines() if line.startswith("| toy |"))
    cells = [c.strip() for c in toy.strip("|").split("|")]
    assert cells[3] == "40"  # the newer run, not the older one nor the quick file
    assert cells[5] == "**0.90**"  # fewer than 95 % converged
    assert cells[6] == "0.200" and cells[7] == "0.300"  # the smallest p-values, bold stripped and not re-added
    assert cells[8] == "0.85-0.90" and cells[9] == "**1.012**" and cells[10] == "450"
    assert "`calibration_b.md` (2026-11-22); older: `calibration_a.md`" in toy
    assert "| missing | pgas |" in text and "no full run yet" in text

    # fixed records: ±1 sd outside 55-85 % and ±3 sd below 95 % in bold, pgas rows tallied per order
    assert "| Matérn-3/2, acc | pgas | 70.0 / 96.0 / 99.0 | **90.0** / 99.0 / 100.0 |" in text
    assert "| Matérn-5/2, acc | ekf | **50.0** / 86.0 / **93.0** |" in text
    assert "Matérn-3/2: 0 of 1, Matérn-5/2: 1 of 1" in text


def _linear_file(path, date, rows):
    path.write_text(
        f"# Nonlinear methods vs the exact answer on linear systems (full)\n\n{date}; x86_64, 2 cores\n\n"
        "| case | method | force | within the rule | converged |\n|---|---|---|---|---|\n"
        + "".join(f"| {case} | {method} | 0.01 | {ok} | {ok} |\n" for case, method, ok in rows),
        encoding="utf-8",
    )


def test_a_linear_case_rerun_in_a_newer_file_replaces_its_older_row(tmp_path):
    """Linear-suite rows are kept as they are, but a (case, method) run again in a newer file (a case
    rerun after a fix) shows that file's row only; the older file's other rows stay."""
    ci = _index()
    _linear_file(
        tmp_path / "linear_suite_a.md", "2026-12-01T10:00:00", [("sdof", "pgas", "yes"), ("sdof", "ekf", "no")]
    )
    _linear_file(tmp_path / "linear_suite_b.md", "2026-12-02T10:00:00", [("sdof", "ekf", "yes")])
    text = ci.build(tmp_path, expected=[])
    rows = [line for line in text.splitlines() if line.startswith("| sdof |")]
    assert len(rows) == 2, rows
    assert any("| pgas |" in r and "linear_suite_a.md" in r for r in rows)
    assert any("| ekf |" in r and "| yes |" in r and "linear_suite_b.md" in r for r in rows)
    assert "**no**" not in text


def test_the_committed_overview_is_up_to_date():
    """``benchmarks/results/calibration.md`` is what the index builds from the committed result files
    (rerun ``python benchmarks/calibration_index.py`` after adding a calibration run)."""
    ci = _index()
    assert ci.main(["--check"]) == 0
