r"""Probe (not a method of the library): NUTS on the whitened force noise of a Duffing model.

The question (issue "Nonlinear posteriors that are right on any case a user
brings"): is a gradient-based sampler on the latent's whitened innovations,
preconditioned by the Gauss-Newton posterior at the mode, a candidate for the
smooth-force (Matérn-3/2 and up) nonlinear cases where ``pgas`` does not mix?
This script measures the geometry that decides it and a short run; it is kept
so that the measurement can be repeated, and its numbers are in
``benchmarks/results/whitened_nuts_probe.md`` and the notes.

The target. :class:`~latentforce.inference.smc.ParticleModel`'s latent
:math:`g_t = (x_{f,t}, w_t)` is linear-Gaussian given the hyperparameters
(``transition``), and the path is a deterministic function of it
(``path``), so with innovations :math:`\varepsilon \sim N(0, I)` and
:math:`g = \mathrm{colour}(\varepsilon)` the posterior is
:math:`\log p(\varepsilon \mid y) = -\tfrac12|\varepsilon|^2 + \log p(y \mid
\mathrm{path}(\varepsilon)) + c`, a smooth density in :math:`T \cdot n_l`
dimensions (4096 for an SDOF Duffing with a Matérn-3/2 force, T = 1024).

The preconditioner. The mode :math:`\hat\varepsilon` by Gauss-Newton from the
extended Kalman smoother's path (5-6 steps to converge to 1e-8 here), then
:math:`H = I + J^T R^{-1} J` (``J`` the Jacobian of the predicted
observations, reverse mode) and :math:`\varepsilon = \hat\varepsilon +
L^{-T} z` with :math:`H = L L^T`; NUTS (blackjax, dual-averaging step size)
runs on ``z`` with a unit mass. For a linear system :math:`z` is exactly
standard normal. Stage 1: a short NUTS run from the mode with that
:math:`H`; stage 2: ``H`` recomputed as the average of the Gauss-Newton
matrices at the mode and at stage 1's chain positions, then warm-up and draws.
The probe reports the largest eigenvalue of :math:`-\nabla^2_z \log p`
(power iteration on Hessian-vector products) at the mode, at a chain
position and at a draw of the Gaussian approximation (:math:`z \sim N(0, I)`):
1 where the posterior is the Gaussian the preconditioner assumes; its square
root bounds the step size from above by about 2 / that.

Usage::

    PYTHONPATH=src python benchmarks/whitened_nuts_probe.py --sensors acc
    PYTHONPATH=src python benchmarks/whitened_nuts_probe.py --sensors acc,disp --draws 200

Each run appends a row to the results table (``--out``).
"""

from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results" / "whitened_nuts_probe.md"
QUANTITY = {"acc": "acceleration", "vel": "velocity", "disp": "displacement"}
HEADER = (
    "| date | order | sensors | k3 | force var | T | nonlinear share | max eig at mode / chain / N(0,I) draw "
    "(stage 1) | same (stage 2) | step | leapfrog steps | draws/chain | force max R-hat | force min ESS "
    "| disp max R-hat | inside ±1/2/3 sd | force NMSE | s (mode / stage 1 / stage 2) "
    "| pgas on the same record: max R-hat / min ESS, inside ±1/2/3 sd, s |\n"
    "|---|---:|---|---:|---:|---:|---:|---|---|---:|---:|---:|---:|---:|---:|---|---:|---|---|\n"
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--order", type=int, default=1, help="Matérn order p (nu = p + 1/2)")
    ap.add_argument("--sensors", default="acc", help="comma list of acc, vel, disp (all at 1 %% noise)")
    ap.add_argument("--k3", type=float, default=1e9)
    ap.add_argument("--variance", type=float, default=100.0, help="force variance (N^2)")
    ap.add_argument("--T", type=int, default=1024)
    ap.add_argument("--stage1", type=int, default=30, help="NUTS iterations with the mode's preconditioner")
    ap.add_argument("--warmup", type=int, default=60, help="stage 2 warm-up iterations")
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--pgas",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="also run pgas (iterations auto, 4 chains, burn-in 2000) for at most this long",
    )
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)

    import arviz as az
    import blackjax
    import jax
    import jax.numpy as jnp
    import jax.scipy.linalg as jsl
    from blackjax.adaptation.step_size import dual_averaging_adaptation

    import latentforce

    latentforce.enable_x64()  # float64; XLA's small-loop threshold before JAX starts
    from latentforce.inference import latent, pgas_start, smc
    from latentforce.kernels import Matern
    from latentforce.models import LatentForceModel, Sensor
    from latentforce.systems import Duffing

    dt, T, lengthscale = 1 / 2048, args.T, 0.02
    kinds = [QUANTITY[s.strip()] for s in args.sensors.split(",")]
    params = dict(m=1.0, c=20.0, k=1e4, k3=args.k3, force_variance=args.variance, force_lengthscale=lengthscale)
    start = (np.zeros(2), np.diag([1e-3, 0.1]) ** 2)

    def particle_model(noise):
        model = LatentForceModel(Duffing(), Matern(args.order), [Sensor(q, 0, s) for q, s in zip(kinds, noise)])
        return smc.ParticleModel(model, params, dt, initial=start)

    # the truth and the record: a draw of the model, 1 % noise on every channel
    pm = particle_model([1.0] * len(kinds))
    tr = pm.transition(args.variance, lengthscale)
    truth = pm.path(latent.gp_prior_path(jax.random.key(args.seed), tr, T))
    clean = jax.vmap(lambda x: pm._observe(x[:2], x[2:]))(truth)
    noise = 0.01 * np.asarray(jnp.std(clean, axis=0))
    y = clean + noise * jax.random.normal(jax.random.key(args.seed + 1), clean.shape)
    pm = particle_model(noise)
    mask = jnp.ones_like(y, dtype=bool)
    od = latent.observation_density(pm, y, mask)
    share = float(jnp.std(args.k3 * truth[:, 0] ** 3) / jnp.std(1e4 * truth[:, 0]))
    nl = pm.nl
    n = T * nl
    scale = jnp.sqrt(jnp.diagonal(od.Rinv, axis1=1, axis2=2))

    def residual(e):
        path = pm.path(latent.colour(tr, e.reshape(T, nl)))
        return ((od.y - latent.predicted_observations(pm, path)) * scale).reshape(-1)

    def log_density(e):
        r = residual(e)
        return -0.5 * jnp.sum(e**2) - 0.5 * jnp.sum(r**2)

    jac = jax.jit(jax.jacrev(residual))

    @jax.jit
    def gauss_newton(e):
        r, J = residual(e), jac(e)
        g = e + J.T @ r
        return e - (g - J.T @ jnp.linalg.solve(jnp.eye(J.shape[0]) + J @ J.T, J @ g))

    t0 = time.perf_counter()
    eks = jax.jit(lambda: pgas_start.extended_kalman_smoother(pm, tr, y, mask))()
    mode = latent.whiten(tr, pm.latent(eks)).reshape(-1)
    for _ in range(8):
        mode = gauss_newton(mode)
    J0 = jac(mode)
    t_mode = time.perf_counter() - t0

    def factor(gram):
        L = jnp.linalg.cholesky(jnp.eye(n) + gram)
        return jsl.solve_triangular(L.T, jnp.eye(n), lower=False)  # L^{-T}

    def max_eig(Lt, z, iters=30):
        ld = lambda z_: log_density(mode + Lt @ z_)  # noqa: E731
        hv = jax.jit(lambda v: jax.jvp(jax.grad(ld), (z,), (v,))[1])
        v = jax.random.normal(jax.random.key(5), (n,))
        lam = 0.0
        for _ in range(iters):
            w = -hv(v)
            lam = float(jnp.linalg.norm(w) / jnp.linalg.norm(v))
            v = w / jnp.linalg.norm(w)
        return lam

    da_init, da_update, da_final = dual_averaging_adaptation(0.8)
    kernel = blackjax.mcmc.nuts.build_kernel()
    unit = jnp.ones(n)

    def nuts(Lt, warm, draws, key, z0, step0):
        ld = lambda z_: log_density(mode + Lt @ z_)  # noqa: E731

        @jax.jit
        def run(keys, z0):
            def chain(k, z):
                def warm_step(c, kk):
                    st, da = c
                    st, info = kernel(kk, st, ld, jnp.exp(da.log_step_size), unit, max_num_doublings=8)
                    acc = jnp.where(jnp.isfinite(info.acceptance_rate), info.acceptance_rate, 0.0)
                    return (st, da_update(da, acc)), info.num_integration_steps

                k1, k2 = jax.random.split(k)
                (st, da), _ = jax.lax.scan(
                    warm_step, (blackjax.mcmc.nuts.init(z, ld), da_init(step0)), jax.random.split(k1, warm)
                )
                h = da_final(da)

                def step(st, kk):
                    st, info = kernel(kk, st, ld, h, unit, max_num_doublings=8)
                    p = pm.path(latent.colour(tr, (mode + Lt @ st.position).reshape(T, nl)))
                    return st, (p[:, 0], p[:, 2], info.num_integration_steps)

                st, out = jax.lax.scan(step, st, jax.random.split(k2, draws))
                return st.position, out, h

            return jax.vmap(chain)(keys, z0)

        return run(jax.random.split(key, 4), z0)

    # stage 1: the mode's Gauss-Newton preconditioner, a short run from the mode
    t0 = time.perf_counter()
    Lt1 = factor(J0.T @ J0)
    z_draw = jax.random.normal(jax.random.key(7), (n,))
    zpos, _, h1 = nuts(Lt1, args.stage1, 1, jax.random.key(4), jnp.zeros((4, n)), 0.5)
    eig1 = (max_eig(Lt1, jnp.zeros(n)), max_eig(Lt1, zpos[0]), max_eig(Lt1, z_draw))
    t_stage1 = time.perf_counter() - t0

    # stage 2: the Gauss-Newton matrices averaged over the mode and the chain positions
    t0 = time.perf_counter()
    eps = mode + zpos @ Lt1.T
    Js = jax.jit(jax.vmap(jac))(eps)
    Lt2 = factor((J0.T @ J0 + jnp.einsum("kmi,kmj->ij", Js, Js)) / 5.0)
    z2 = jnp.linalg.solve(Lt2, (eps - mode).T).T
    eig2 = (max_eig(Lt2, jnp.zeros(n)), max_eig(Lt2, z2[0]), max_eig(Lt2, z_draw))
    _, (disp, force, steps), h2 = nuts(Lt2, args.warmup, args.draws, jax.random.key(6), z2, float(jnp.mean(h1)))
    force = np.asarray(force)
    disp = np.asarray(disp)
    t_stage2 = time.perf_counter() - t0

    f_true = np.asarray(truth[:, 2])
    mean, sd = force.mean((0, 1)), force.std((0, 1))
    idx = np.linspace(0, T - 1, 24).astype(int)
    rhat_f = max(float(az.rhat(force[:, :, i])) for i in idx)
    ess_f = min(float(az.ess(force[:, :, i])) for i in idx)
    rhat_d = max(float(az.rhat(disp[:, :, i])) for i in idx)
    inside = [float(np.mean(np.abs(f_true - mean) < k * sd)) for k in (1, 2, 3)]
    nmse = float(np.mean((mean - f_true) ** 2) / np.var(f_true))

    pgas_cell = "not run"
    if args.pgas > 0:
        from latentforce.inference.pgas import run_pgas

        t0 = time.perf_counter()
        out = run_pgas(
            jax.random.key(args.seed + 2),
            pm.model,
            params,
            {},
            y,
            mask,
            dt,
            iterations=None,
            burn_in=2000,
            chains=4,
            initial=start,
            max_time=args.pgas,
        )
        verdict = out.diagnostics["convergence"]
        pm_mean, pm_sd = out.state_mean["force"][:, 0], out.state_sd["force"][:, 0]
        pin = [float(np.mean(np.abs(f_true - pm_mean) < k * pm_sd)) for k in (1, 2, 3)]
        pgas_cell = (
            f"{verdict['max_r_hat']:.3f} / {verdict['min_ess_bulk']:.0f}, "
            + " / ".join(f"{100 * v:.1f} %" for v in pin)
            + f", {time.perf_counter() - t0:.0f} s"
        )

    def eigs(e):
        return " / ".join(f"{v:.3g}" for v in e)

    row = (
        f"| {datetime.date.today()} | {args.order} | {args.sensors} | {args.k3:g} | {args.variance:g} | {T} | "
        f"{share:.2f} | {eigs(eig1)} | {eigs(eig2)} | {float(np.mean(h2)):.3f} | {float(np.mean(steps)):.0f} | "
        f"{args.draws} (+{args.stage1}+{args.warmup}) | {rhat_f:.3f} | {ess_f:.0f} | {rhat_d:.3f} | "
        + " / ".join(f"{100 * v:.1f} %" for v in inside)
        + f" | {nmse:.2e} | {t_mode:.1f} / {t_stage1:.1f} / {t_stage2:.1f} | {pgas_cell} |\n"
    )
    print(HEADER + row)
    if not args.out.exists():
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(
            "# NUTS on the whitened force noise: probe runs (benchmarks/whitened_nuts_probe.py)\n\n"
            "Duffing m = 1, c = 20, k = 1e4, 2048 Hz, Matérn force lengthscale 0.02 s, "
            "hyperparameters fixed at the truth, 4 chains, 2-core machine.\n\n" + HEADER
        )
    with args.out.open("a") as fh:
        fh.write(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
