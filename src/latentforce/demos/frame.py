r"""``latentforce demo frame``: a 3-storey shear frame with a hysteretic storey, the force at the top
and accelerations at two floors.

A laboratory-scale frame: floors of 5 kg, storeys of 1e4 N/m and 10 N s/m (modes at 3.2, 8.9 and
12.8 Hz without the brace). Between floors 0 and 1 a Bouc-Wen element (a yielding brace or a friction damper) adds
its hysteretic force :math:`r` to the storey's spring:

.. math:: \dot r = \alpha\,\dot\delta - \beta|\dot\delta||r|^{\nu-1}r - \gamma\,\dot\delta|r|^\nu,
          \qquad \delta = z_1 - z_0,

alpha = 1e4 N/m (doubling the storey's stiffness at small drifts), beta = 60 /m, gamma = 20 /m,
nu = 1: the brace's force saturates at alpha / (beta + gamma) = 125 N on loading and its tangent
returns to alpha on unloading, a loop well away from the linear one. The force at
the top floor is a Matérn-1/2 GP of 50 N rms and lengthscale 0.05 s; 4 s at 100 Hz from rest
(``--quick``: 1.5 s).
Accelerometers on floors 0 and 2 with 1 % RMS noise each: no displacement sensor.

``pgas`` infers the three floors' motion, the brace's hysteretic force and the force with its
variance and lengthscale (log-normal priors, not centred on the truth); the frame is known. The
run stops once converged (``--quick``: a short smoke run). Figures as for every run, and
``figures/hysteresis.png``: the brace's force against the storey's drift.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from latentforce.demos.common import echo_truth_report, preload_modules, write_case
from latentforce.results import check_out_dir

FLOORS = 3
BRACE = {"type": "bouc-wen", "dofs": [1, 0], "alpha": 1.0e4, "beta": 60.0, "gamma": 20.0, "nu": 1.0}
SYSTEM = {
    "type": "linear",
    "masses": [5.0] * FLOORS,
    "dampings": [10.0] * FLOORS,
    "stiffnesses": [1.0e4] * FLOORS,
    "force_dofs": [FLOORS - 1],
    "elements": [BRACE],
}
FS = 100.0
DURATION = 4.0
QUICK_DURATION = 1.5  # --quick: a smoke run
TRUE_VARIANCE, TRUE_LENGTHSCALE = 2500.0, 0.05
TRUE = {"force_variance": TRUE_VARIANCE, "force_lengthscale": TRUE_LENGTHSCALE}
SENSOR_FLOORS = (0, 2)


def _problem():
    from latentforce.io.config import config_from_dict

    cfg = {
        "system": SYSTEM,
        "force": {"kernel": "matern12", "variance": TRUE_VARIANCE, "lengthscale": TRUE_LENGTHSCALE},
        "sensors": [
            {"column": f"acc{f}", "quantity": "acceleration", "dof": f, "noise_std": 1.0} for f in SENSOR_FLOORS
        ],
    }
    return config_from_dict(cfg, source="frame demo")


def simulate(seed: int, duration: float = DURATION) -> tuple[dict, dict]:
    """``(columns, noise_sd)``: the record of ``seed`` with its truth columns (every floor's
    displacement and velocity, the brace's force, the force) and 1 % RMS noise on each
    accelerometer (from ``seed + 1``)."""
    import jax

    from latentforce.simulate import simulate as simulate_fn

    problem = _problem()
    params = {**problem.fixed, **TRUE}
    n = int(round(duration * FS))
    sim = simulate_fn(jax.random.key(seed), problem.model, params, n, 1.0 / FS, substeps=16)
    rng = np.random.default_rng(seed + 1)
    columns, noise = {"time": sim.time}, {}
    for f in SENSOR_FLOORS:
        acc = sim.acceleration[:, f]
        noise[f"acc{f}"] = 0.01 * float(np.sqrt(np.mean(acc**2)))
        columns[f"acc{f}"] = acc + noise[f"acc{f}"] * rng.normal(size=n)
    for f in range(FLOORS):
        columns[f"displacement_{f}"] = sim.displacement[:, f]
    for f in range(FLOORS):
        columns[f"velocity_{f}"] = sim.velocity[:, f]
    columns["hysteretic_force"] = sim.hysteretic_force[:, 0]
    columns["force"] = sim.force[:, 0]
    return columns, noise


def config(noise: dict, quick: bool, seed: int) -> dict:
    counts = (
        {"chains": 2, "iterations": 150, "burn_in": 50, "thin_draws": 50}
        if quick
        else {"chains": 4, "iterations": "auto", "burn_in": 1000, "thin_draws": 200}
    )
    return {
        "data": {"time_column": "time", "missing": "error"},
        "system": {**SYSTEM, "elements": [dict(BRACE)]},
        "force": {
            "kernel": "matern12",
            "variance": {"prior": "lognormal", "mu": float(np.log(1000.0)), "sigma": 1.5, "init": 1000.0},
            "lengthscale": {"prior": "lognormal", "mu": float(np.log(0.1)), "sigma": 1.5, "init": 0.1},
        },
        "sensors": [
            {"column": c, "quantity": "acceleration", "dof": int(c.removeprefix("acc")), "noise_std": sd}
            for c, sd in noise.items()
        ],
        "inference": {"method": "pgas", "particles": 50, "state_every": 5, "mh_steps": 5, "seed": seed, **counts},
    }


def run_frame(out: Path, quick: bool = False, seed: int = 0, overwrite: bool = False, echo=print, progress=None):
    out = Path(out)
    check_out_dir(out, overwrite)
    t0 = time.perf_counter()
    preload_modules()
    columns, noise = simulate(seed, QUICK_DURATION if quick else DURATION)
    drift = columns["displacement_1"] - columns["displacement_0"]
    echo(
        f"frame demo: a {FLOORS}-storey shear frame (5 kg floors, 1e4 N/m storeys) with a Bouc-Wen brace "
        f"between floors 0 and 1 (alpha=1e4, beta=60, gamma=20, nu=1) at {FS:g} Hz, {len(drift)} samples; a "
        f"Matérn-1/2 force of {np.sqrt(TRUE_VARIANCE):g} N rms at the top; storey drift up to "
        f"{1e3 * np.max(np.abs(drift)):.1f} mm, brace force up to {np.max(np.abs(columns['hysteretic_force'])):.0f} N; "
        "accelerations of floors 0 and 2, 1 % RMS noise each; the force's variance and lengthscale inferred"
    )
    _, _, result, _ = write_case(
        out, config(noise, quick, seed), columns, overwrite=True, seed=seed, diagnostics={"true_params": TRUE}
    )
    echo_truth_report(result, TRUE, echo, t0, out, " (figures/hysteresis.png: the brace's loop)")
