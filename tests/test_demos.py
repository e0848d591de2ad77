"""Every demo's ``--quick`` path through the command line: it finishes, writes its result
folders (the main case and its variants) with a summary that has the truth's NMSE, and says
whether it converged."""

import json

import pytest
from typer.testing import CliRunner

from latentforce.cli import app

#: the subfolders each demo writes beside its main case (INTERFACE.md, `demo`)
VARIANTS = {
    "oma": ["known-system"],
    "duffing": ["with-displacement"],
    "duffing-params": [],
    "bouc-wen": [],
    "frame": [],
    "sine": [],
}


# sine under -m slow (46 s on 2026-12-02's slow 2-core machine): the duffing demo's own code with
# another force, which the duffing demo runs in CI
@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n == "sine" else n for n in sorted(VARIANTS)]
)
def test_a_quick_demo_writes_its_result_folders(tmp_path, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["demo", name, "--quick", "--out", "d"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "d" / "data.csv").is_file()
    for folder in [tmp_path / "d"] + [tmp_path / "d" / v for v in VARIANTS[name]]:
        summary = json.loads((folder / "summary.json").read_text())
        # an MDOF structure reports each floor's displacement (displacement_0, ...)
        assert "force" in summary["nmse"] and any(k.startswith("displacement") for k in summary["nmse"]), folder
        assert isinstance(summary["converged"], bool), folder
        assert (folder / "figures" / "force.png").stat().st_size > 1000, folder
        assert (folder / "posterior.nc").is_file() and (folder / "summary.csv").is_file(), folder
    if name == "bouc-wen":  # the internal states' start-up move runs (fixed system parameters; 0.60-0.63)
        moved = json.loads((tmp_path / "d" / "summary.json").read_text())["diagnostics"]["acceptance_internal"]
        assert len(moved) >= 2 and min(moved) > 0.05, moved
        # and the profile move (profile_move)
        prof = json.loads((tmp_path / "d" / "summary.json").read_text())["diagnostics"]["acceptance_profile"]
        assert len(prof) >= 2 and min(prof) > 0.05, prof
