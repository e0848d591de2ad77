"""PGAS against the exact Kalman smoother on the linear analogue of the Duffing case.

The longer companion of tests/test_pgas.py::test_pgas_matches_kalman_smoother:
m = 1, c = 20, k = 1e4 (k3 = 0), Matérn-1/2 force (variance 20, lengthscale
0.1 s), 2048 Hz, 1 % RMS noise; acceleration only (the paper's case) and with
a displacement channel. The data come from the exact (Van Loan)
discretisation of the continuous model and the reference is its Kalman
smoother. Hyperparameters fixed, 4 dispersed chains. Reports,
per state, the NMSE between the PGAS and Kalman posterior means (relative to
the variance of the Kalman mean), the mean |sd ratio - 1|, the max R-hat at 5
time points and the ancestor switch rate, and writes the table to
benchmarks/results/pgas_exactness.md.

Usage: python benchmarks/pgas_exactness.py [--quick] [--T 1024] [--iterations 2000]
       [--lowfreq-modes 16] [--lowfreq-steps 5]
"""

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import latentforce

latentforce.enable_x64()  # float64; XLA's small-loop threshold before JAX starts
from latentforce.inference import pgas, smc
from latentforce.inference.kalman import kalman_smoother
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.systems import LinearSystem

PARAMS = dict(m=1.0, c=20.0, k=1.0e4, force_variance=20.0, force_lengthscale=0.1)


def case(
    sensors_kind: str,
    T: int,
    iterations: int,
    burn_in: int,
    particles: int,
    seed: int = 0,
    lowfreq_modes: int = 16,
    lowfreq_steps: int = 5,
):
    dt = 1 / 2048
    quantities = ["acceleration"] + (["displacement"] if sensors_kind == "acc+disp" else [])
    # Simulate from the exact discretisation of the continuous model (noise set after a dry run);
    # the reference is the Kalman smoother of that same exact model.
    model0 = LatentForceModel(LinearSystem(), Matern(0), [Sensor(q, 0, 1.0) for q in quantities])
    A_d, Q_d = model0.discretise(PARAMS, dt)
    H0, _ = model0.observation(PARAMS)
    pm0 = smc.ParticleModel(model0, PARAMS, dt)
    m0f = np.concatenate([np.asarray(pm0.mech0_mean), np.zeros(pm0.nfx)])
    P0 = np.asarray(
        jax.scipy.linalg.block_diag(
            pm0.mech0_cov, pm0.force_transition(PARAMS["force_variance"], PARAMS["force_lengthscale"])[2]
        )
    )
    rng = np.random.default_rng(seed)
    x = rng.multivariate_normal(m0f, P0)
    clean = []
    for _ in range(T):
        clean.append(np.asarray(H0) @ x)
        x = np.asarray(A_d) @ x + rng.multivariate_normal(np.zeros(pm0.n_state), np.asarray(Q_d))
    clean = np.array(clean)
    noise = 0.01 * np.sqrt(np.mean(clean**2, axis=0))
    y = clean + rng.normal(size=clean.shape) * noise
    model = LatentForceModel(LinearSystem(), Matern(0), [Sensor(q, 0, float(s)) for q, s in zip(quantities, noise)])
    H, R = model.observation(PARAMS)
    mask = jnp.ones(y.shape, bool)
    ks = kalman_smoother(A_d, Q_d, H, R, jnp.asarray(m0f), jnp.asarray(P0), jnp.asarray(y), mask)
    t0 = time.perf_counter()
    out = pgas.run_pgas(
        jax.random.key(seed, impl="rbg"),
        model,
        PARAMS,
        {},
        jnp.asarray(y),
        mask,
        dt,
        particles=particles,
        iterations=iterations,
        burn_in=burn_in,
        state_every=1,
        chains=4,
        lowfreq_modes=lowfreq_modes,
        lowfreq_steps=lowfreq_steps,
    )
    wall = time.perf_counter() - t0
    km = np.asarray(ks.means)
    ksd = np.sqrt(np.asarray(jnp.diagonal(ks.covs, axis1=1, axis2=2)))
    rows = []
    for name, i in (("displacement", 0), ("velocity", 1), ("force", 2)):
        mean, sd = out.state_mean[name][:, 0], out.state_sd[name][:, 0]
        nmse = 100 * np.mean((mean - km[:, i]) ** 2) / np.var(km[:, i])
        ratio = np.mean(np.abs(sd / ksd[:, i] - 1))
        rows.append((sensors_kind, name, nmse, ratio))
    rhat = max(v for k, v in out.diagnostics["rhat"].items() if k.startswith("force["))
    acc_lf = float(np.mean(out.diagnostics["acceptance_lowfreq"]))
    return rows, rhat, float(np.mean(out.diagnostics["switch_rate"])), acc_lf, wall


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--T", type=int, default=1024)
    ap.add_argument("--iterations", type=int, default=2000)
    ap.add_argument("--particles", type=int, default=50)
    ap.add_argument("--lowfreq-modes", type=int, default=16)
    ap.add_argument("--lowfreq-steps", type=int, default=5, help="0 disables the low-frequency move")
    a = ap.parse_args()
    T, it = (256, 300) if a.quick else (a.T, a.iterations)
    lines = [
        f"PGAS vs exact Kalman smoother, linear analogue of the Duffing case, T = {T}, "
        f"N = {a.particles}, 4 chains x {it} sweeps (+{it // 4} burn-in), hyperparameters fixed, "
        f"{a.lowfreq_steps} low-frequency moves ({a.lowfreq_modes} modes) per sweep",
        "",
        "| sensors | state | NMSE of PGAS mean vs Kalman mean [%] | mean abs(sd ratio - 1) | "
        "max force R-hat | switch rate | low-freq acceptance | wall [s] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for kind in ("acc", "acc+disp"):
        rows, rhat, sw, acc_lf, wall = case(
            kind, T, it, it // 4, a.particles, lowfreq_modes=a.lowfreq_modes, lowfreq_steps=a.lowfreq_steps
        )
        for s, name, nmse, ratio in rows:
            lines.append(
                f"| {s} | {name} | {nmse:.4f} | {ratio:.3f} | {rhat:.3f} | {sw:.2f} | {acc_lf:.2f} | {wall:.0f} |"
            )
    text = "\n".join(lines)
    print(text)
    out = Path(__file__).parent / "results" / ("pgas_exactness_quick.md" if a.quick else "pgas_exactness.md")
    out.parent.mkdir(exist_ok=True)
    out.write_text(text + "\n")


if __name__ == "__main__":
    main()
