r"""``latentforce demo bouc-wen``: the hysteresis loop of a Bouc-Wen oscillator, recovered with bands.

The system of the nonlinear system identification benchmark of Noël &
Schoukens (2016): :math:`m\ddot z + c\dot z + k z + r = u`,
:math:`\dot r = \alpha\dot z - \beta|\dot z||r|^{\nu-1}r - \gamma\dot z|r|^\nu` with
m = 2 kg, c = 10 N s/m, k = 5e4 N/m, alpha = 5e4 N/m, beta = 800 m^-1,
gamma = -1100 m^-1, nu = 1 (the benchmark's beta*gamma and beta*delta), at
its 750 Hz. The force is a Matérn-1/2 GP of 50 N rms and lengthscale
0.01 s (the benchmark excites with a 50 N rms multisine), 0.6 s from rest:
displacements of 1-2 mm and a hysteretic force of up to 200 N, a loop well
away from the linear one. An accelerometer and a displacement sensor, 1 %
RMS noise each.

``pgas`` infers the hysteretic force as a state and the force's variance
and lengthscale (log-normal priors, not centred on the truth); the system is
known. (Its parameters may be priors too, ``docs/nonlinear.md``; on this
record beta mixed slowly: the linearised proposals that move system
parameters accepted 6-18 % here, against 60 % on the Duffing demos.) The
run stops once converged (``--quick``: a short smoke run). Besides the usual
figures, ``figures/hysteresis.png``: the restoring force r against the
displacement, posterior mean, sampled loops and the 90 % band, the truth
dashed; ``figures/hysteretic_force.png`` the same against time.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from latentforce.demos.common import echo_truth_report, noisy_record, preload_modules, write_case
from latentforce.results import check_out_dir

SYSTEM = {
    "type": "bouc-wen",
    "m": 2.0,
    "c": 10.0,
    "k": 5.0e4,
    "alpha": 5.0e4,
    "beta": 800.0,
    "gamma": -1100.0,
    "nu": 1.0,
}
FS = 750.0
DURATION = 0.6
TRUE_VARIANCE, TRUE_LENGTHSCALE = 2500.0, 0.01
TRUE = {"force_variance": TRUE_VARIANCE, "force_lengthscale": TRUE_LENGTHSCALE}


def simulate(seed: int) -> tuple[dict, float, float]:
    """``(columns, acc_sd, disp_sd)``: the record of ``seed`` with its truth columns, 1 % RMS noise."""
    import jax

    from latentforce.kernels import Matern
    from latentforce.models import LatentForceModel, Sensor
    from latentforce.simulate import simulate as simulate_fn
    from latentforce.systems import BoucWen

    n = int(round(DURATION * FS))
    model = LatentForceModel(BoucWen(), Matern(0), [Sensor("acceleration", 0, 1.0)])
    params = dict(
        {k: v for k, v in SYSTEM.items() if k != "type"},
        force_variance=TRUE_VARIANCE,
        force_lengthscale=TRUE_LENGTHSCALE,
    )
    sim = simulate_fn(jax.random.key(seed), model, params, n, 1.0 / FS, substeps=16)
    return noisy_record(sim, seed)


def config(acc_sd: float, disp_sd: float, quick: bool, seed: int) -> dict:
    counts = (
        {"chains": 2, "iterations": 600, "burn_in": 200, "thin_draws": 50}
        if quick
        else {"chains": 4, "iterations": "auto", "burn_in": 2000, "thin_draws": 200}
    )
    return {
        "data": {"time_column": "time", "missing": "error"},
        "system": dict(SYSTEM),
        "force": {
            "kernel": "matern12",
            "variance": {"prior": "lognormal", "mu": float(np.log(1000.0)), "sigma": 1.5, "init": 1000.0},
            "lengthscale": {"prior": "lognormal", "mu": float(np.log(0.03)), "sigma": 1.5, "init": 0.03},
        },
        "sensors": [
            {"column": "acc", "quantity": "acceleration", "dof": 0, "noise_std": acc_sd},
            {"column": "disp", "quantity": "displacement", "dof": 0, "noise_std": disp_sd},
        ],
        "inference": {"method": "pgas", "particles": 50, "state_every": 5, "mh_steps": 5, "seed": seed, **counts},
    }


def run_bouc_wen(out: Path, quick: bool = False, seed: int = 0, overwrite: bool = False, echo=print, progress=None):
    out = Path(out)
    check_out_dir(out, overwrite)
    t0 = time.perf_counter()
    preload_modules()
    columns, acc_sd, disp_sd = simulate(seed)
    r, z = columns["hysteretic_force"], columns["displacement"]
    echo(
        "bouc-wen demo: the Noël-Schoukens benchmark oscillator (m=2, c=10, k=5e4, alpha=5e4, beta=800, "
        f"gamma=-1100, nu=1) at {FS:g} Hz, {len(z)} samples; a Matérn-1/2 force of {np.sqrt(TRUE_VARIANCE):g} N rms; "
        f"|z| up to {1e3 * np.max(np.abs(z)):.2f} mm, |r| up to {np.max(np.abs(r)):.0f} N; acceleration and "
        "displacement, 1 % RMS noise each; the force's variance and lengthscale inferred"
    )
    _, _, result, _ = write_case(
        out, config(acc_sd, disp_sd, quick, seed), columns, overwrite=True, seed=seed, diagnostics={"true_params": TRUE}
    )
    echo_truth_report(result, TRUE, echo, t0, out, " (figures/hysteresis.png: the loop)")
