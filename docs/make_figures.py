"""Figures for the docs (run: python docs/make_figures.py). Deterministic (fixed seeds).

oma_force.png (with a demo folder as argument: python docs/make_figures.py demo-oma):
the README figure.

acc_only_bands.png: the exact Kalman smoother on the linear analogue of the
Vibration 2020 Duffing case (k3 = 0), acceleration only vs acceleration +
displacement, with the transfer function that explains the difference.
"""

from pathlib import Path

import jax
import numpy as np
from matplotlib.figure import Figure

import latentforce

latentforce.enable_x64()  # float64; XLA's small-loop threshold before JAX starts
from latentforce.inference.kalman_mcmc import Initial, smooth, state_moments
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.results import coverage, nmse
from latentforce.simulate import simulate
from latentforce.systems import LinearSystem

OUT = Path(__file__).parent / "images"


def rest_start(model, params):
    """The nonlinear default: start near rest (0.1 x stationary sd on z, v), force stationary."""
    _, P = model.stationary_initial(params)
    sd = np.sqrt(np.diag(np.asarray(P)))
    sd[: model.n_mech] *= 0.1
    return Initial(np.zeros(model.n_state), sd)


def acc_only_bands(seeds=range(8), start="rest"):
    params = dict(m=1.0, c=20.0, k=1.0e4, force_variance=20.0, force_lengthscale=0.1)
    dt, n = 1 / 2048, 1024
    base = LatentForceModel(LinearSystem(), Matern(0), [Sensor("acceleration", 0, 1.0)])
    rows, shown = [], None
    for seed in seeds:
        sim = simulate(jax.random.key(seed), base, params, n, dt)
        rng = np.random.default_rng(seed)
        acc, disp = sim.acceleration[:, 0], sim.displacement[:, 0]
        sa, sd_ = 0.01 * np.sqrt(np.mean(acc**2)), 0.01 * np.sqrt(np.mean(disp**2))
        y_acc = acc + sa * rng.normal(size=n)
        y_disp = disp + sd_ * rng.normal(size=n)
        res = {}
        for label, sensors, y in (
            ("acceleration only", [Sensor("acceleration", 0, sa)], y_acc[:, None]),
            (
                "acceleration + displacement",
                [Sensor("acceleration", 0, sa), Sensor("displacement", 0, sd_)],
                np.stack([y_acc, y_disp], 1),
            ),
        ):
            model = LatentForceModel(LinearSystem(), Matern(0), sensors)
            initial = rest_start(model, params) if start == "rest" else None
            sm = smooth(model, params, y, np.ones_like(y, bool), dt, initial)
            mom = state_moments(model, sm.means, sm.covs)
            m, s = (np.asarray(a)[:, 0] for a in mom["force"])
            res[label] = (m, s)
            rows.append(
                (
                    start,
                    seed,
                    label,
                    nmse(sim.force[:, 0], m),
                    coverage(sim.force[:, 0], m, s),
                    float(np.mean(s**2)) / params["force_variance"],
                )
            )
        if shown is None and start == "rest":
            shown = (sim, res)
    if shown is None:
        return rows
    sim, res = shown
    fig = Figure(figsize=(10, 7.5))
    axes = fig.subplots(3, 1)
    for ax, (label, (m, s)) in zip(axes[:2], res.items()):
        for k, alpha in ((3, 0.15), (2, 0.25), (1, 0.4)):
            ax.fill_between(sim.time, m - k * s, m + k * s, color="tab:blue", alpha=alpha, lw=0, label=f"±{k} sd")
        ax.plot(sim.time, m, color="tab:blue", lw=1, label="posterior mean")
        ax.plot(sim.time, sim.force[:, 0], color="red", lw=0.8, ls="--", label="truth")
        ax.set_title(f"Force, exact smoother, {label}", fontsize=10, loc="left")
        ax.set_ylabel("force [N]")
    axes[0].legend(ncol=5, fontsize=8, loc="lower left")
    axes[1].set_xlabel("time [s]")
    w = np.logspace(0, 4, 400)
    H = 1.0 / (params["k"] - params["m"] * w**2 + 1j * params["c"] * w)
    axes[2].loglog(w, np.abs(-(w**2) * H), label="force → acceleration  |ω² H(ω)|")
    axes[2].loglog(w, np.abs(H), label="force → displacement  |H(ω)|")
    axes[2].axvline(1 / params["force_lengthscale"], color="grey", ls=":", label="1/ℓ of the force")
    axes[2].set_xlabel("ω [rad/s]")
    axes[2].set_ylabel("gain")
    axes[2].legend(fontsize=8)
    fig.tight_layout()
    OUT.mkdir(exist_ok=True)
    fig.savefig(OUT / "acc_only_bands.png", dpi=110)
    return rows


def oma_readme_figure(result_dir: Path, window=(0.0, 400.0)):
    """README figure from a `latentforce demo oma` result folder: force and displacement, zoomed."""
    import csv

    with open(result_dir / "summary.csv") as f:
        rows = list(csv.DictReader(f))
    with open(result_dir / "data.csv") as f:
        data = list(csv.DictReader(f))
    t = np.array([float(r["time"]) for r in rows])
    keep = (t >= window[0]) & (t <= window[1])
    fig = Figure(figsize=(10, 5.5))
    axes = fig.subplots(2, 1, sharex=True)
    for ax, name, unit in ((axes[0], "force", "N"), (axes[1], "displacement", "m")):
        m = np.array([float(r[f"{name}_mean"]) for r in rows])[keep]
        s = np.array([float(r[f"{name}_sd"]) for r in rows])[keep]
        truth = np.array([float(r[name]) for r in data])[keep]
        for k, alpha in ((3, 0.15), (2, 0.25), (1, 0.4)):
            ax.fill_between(
                t[keep],
                m - k * s,
                m + k * s,
                color="tab:blue",
                alpha=alpha,
                lw=0,
                label=f"±{k} sd" if name == "force" else None,
            )
        ax.plot(t[keep], m, color="tab:blue", lw=1.2, label="posterior mean")
        ax.plot(t[keep], truth, color="red", lw=1.0, ls="--", label="truth")
        ax.set_ylabel(f"{name} [{unit}]")
    if "disp" in data[0]:
        meas = np.array([float(r["disp"]) for r in data])[keep]
        axes[1].plot(t[keep], meas, ".", ms=2, color="k", alpha=0.5, label="measured")
    axes[0].legend(ncol=5, fontsize=8, loc="upper right")
    axes[1].legend(ncol=3, fontsize=8, loc="lower left")
    axes[1].set_xlabel("time [s]")
    axes[0].set_title(
        "Unmeasured wave force recovered from noisy displacement; k and c inferred too (latentforce demo oma)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(OUT / "oma_force.png", dpi=110)


if __name__ == "__main__":
    import sys

    if len(sys.argv) > 1:  # a `latentforce demo oma` result folder
        oma_readme_figure(Path(sys.argv[1]))
    rows = acc_only_bands(start="rest") + acc_only_bands(start="stationary")
    for start, seed, label, nm, cov, ratio in rows:
        print(
            f"{start:10s} seed {seed}  {label:28s}  force NMSE {nm:6.2f} %   within 3 sd {100 * cov:5.1f} %   "
            f"posterior var / prior var {ratio:.3f}"
        )
