"""The README's worked example from a vendor file: a UFF 58b file with two accelerometers in g at
two sample rates, to a virtual strain with bands and the force spectrum.

    python docs/uff_example.py [FOLDER]     # default: a temporary folder; figures -> docs/images/

Writes FOLDER/frame.uff (by pyuff, as acquisition software would) and FOLDER/frame.toml, runs
``latentforce estimate`` on them, and copies the strain and spectrum figures to docs/images/.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

CONFIG = """\
# A two-storey frame, wind-type load at the roof; accelerometers on both floors.
[data]
path = "frame.uff"               # UFF 58b: channels by their id1 line, time from each record

[system]
type = "linear"
masses = [2000.0, 1500.0]        # kg per floor
dampings = [800.0, 600.0]        # N s/m per storey
stiffnesses = [4.0e6, 3.0e6]     # N/m per storey
force_dofs = [1]                 # the load acts on the roof

[force]
kernel = "matern32"
variance = 1.0e6                 # N^2
lengthscale = 0.05               # s

[[sensors]]
column = "floor1 acc"            # the record's id1
quantity = "acceleration"
dof = 0
unit = "g"                       # the file says g too; stated here for the reader
noise_std = 0.002                # in g

[[sensors]]
column = "roof acc"
quantity = "acceleration"
dof = 1
noise_std = 0.002                # g, from the file's ordinate label

[[outputs]]                      # a strain gauge nobody fitted: the column base of storey 2,
name = "weld_strain"             # strain = 150 microstrain per mm of inter-storey drift
unit = "microstrain"
displacement = [-1.5e5, 1.5e5]

[inference]
method = "kalman"
"""


def write_uff(folder: Path, seed: int = 0) -> None:
    """Simulate the frame (latentforce's own simulator) and write what a data logger would:
    the first floor at 200 Hz, the roof at 100 Hz, both in g."""
    import jax
    import pyuff

    import latentforce

    latentforce.enable_x64()
    import tomllib

    from latentforce.io.config import config_from_dict, initial_params
    from latentforce.simulate import simulate

    problem = config_from_dict(tomllib.loads(CONFIG), base_dir=folder)
    model = problem.model
    sim = simulate(jax.random.key(seed), model, initial_params(problem), 4001, 1 / 200)
    rng = np.random.default_rng(seed)
    g = 9.80665
    records = [("floor1 acc", sim.acceleration[:, 0] / g, 1 / 200), ("roof acc", sim.acceleration[::2, 1] / g, 1 / 100)]
    sets = []
    for name, data, dt in records:
        data = data + 0.002 * rng.standard_normal(data.size)
        sets.append(
            pyuff.prepare_58(
                binary=True,
                func_type=1,
                rsp_node=1,
                rsp_dir=1,
                ref_node=0,
                ref_dir=0,
                id1=name,
                data=data,
                x=dt * np.arange(data.size),
                abscissa_spacing=1,
                abscissa_spec_data_type=17,
                ordinate_spec_data_type=12,
                orddenom_spec_data_type=0,
                z_axis_spec_data_type=0,
                ordinate_axis_units_lab="g",
                abscissa_axis_units_lab="s",
            )
        )
    path = folder / "frame.uff"
    if path.exists():
        path.unlink()
    pyuff.UFF(str(path)).write_sets(sets, mode="add")  # pyuff 2.5.8: "overwrite" corrupts a 58b header


def main(argv: list[str]) -> int:
    folder = Path(argv[1]) if len(argv) > 1 else Path(tempfile.mkdtemp(prefix="uff-example-"))
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "frame.toml").write_text(CONFIG)
    write_uff(folder)
    out = folder / "results"
    subprocess.run(
        [sys.executable, "-m", "latentforce.cli", "estimate", str(folder / "frame.toml"), "--out", str(out), "--force"],
        check=True,
    )
    images = Path(__file__).resolve().parent / "images"
    for name in ("output_weld_strain.png", "force_psd.png"):
        shutil.copy(out / "figures" / name, images / f"uff_{name}")
    print(f"example in {folder}; figures copied to {images}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
