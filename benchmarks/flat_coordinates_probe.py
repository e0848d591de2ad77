r"""Probe (not a method of the library): the acceleration-only smooth-force Duffing posterior in three coordinates.

The question (issue "Nonlinear posteriors that are right on any case a user
brings", its open item: acceleration alone, Matérn-3/2 and smoother forces, a
stiffening structure, where ``pgas`` ends NOT CONVERGED at the 3-minute cap):
is the posterior multimodal (then tempering or mode jumps), or one mode whose
geometry defeats local moves, and in which coordinates is it closest to
Gaussian? The record is ``nonlinear_calibration.py``'s small case (Duffing
m = 1, c = 2, k = 400, 100 Hz, force variance 100, lengthscale 0.05 s, 1 %
noise, seed 0), hyperparameters at the truth.

1. ``--modes N``: ``pgas`` (N chains, 300 + 600 iterations) and then
   Levenberg-Marquardt on the whitened latent from each chain's last path and
   from the extended Kalman smoother: distinct local modes or one.
2. Laplace importance sampling in (a) the whitened latent :math:`\varepsilon`
   (the smoother move's and NUTS probe's coordinates), (b) the state path
   (centred), (c) the *flat* coordinates of the residual-preserving move
   (:class:`~latentforce.inference.path_moves.ResidualMove`) at every sample:
   the within-step noise ``w``, the accelerometer's noise-free prediction and
   the force derivatives' remainders ``h``; the force is solved from the
   prediction sample by sample. All three maps have a constant Jacobian, so
   the posterior is the same density up to a constant and the mode the same
   point. Reported: the excess of :math:`-\log p` over the mode at Laplace
   draws (a Gaussian: ``n/2``) and the log importance weights' sd, at the
   Laplace's own scale and at 0.3 of it.
3. NUTS (blackjax) in the flat coordinates, preconditioned by the Laplace
   there (stage 1, unit mass), then (stage 2) with a mass matrix adapted
   from stage 1's draws: the identity plus the eigen-directions of their
   covariance wider than 1.5 (low rank), 4 chains from stage 1's ends;
   ``--stages N`` repeats that, each stage's mass from the one before.

Usage::

    PYTHONPATH=src python benchmarks/flat_coordinates_probe.py --order 2 --modes 8
    PYTHONPATH=src python benchmarks/flat_coordinates_probe.py --order 2 --warmup 200 --draws 300
    PYTHONPATH=src python benchmarks/flat_coordinates_probe.py --order 2 --stages 4

Measured numbers: ``benchmarks/results/flat_coordinates_probe.md`` and docs/nonlinear.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--order", type=int, default=2, help="Matérn order p (nu = p + 1/2)")
    ap.add_argument("--k3", type=float, default=4e5)
    ap.add_argument("--sensors", default="acc")
    ap.add_argument("--T", type=int, default=256)
    ap.add_argument("--modes", type=int, default=0, metavar="CHAINS", help="run the mode search from pgas chains")
    ap.add_argument("--warmup", type=int, default=200, help="NUTS warm-up iterations a stage (0: no NUTS)")
    ap.add_argument("--draws", type=int, default=300, help="NUTS draws a stage and chain")
    ap.add_argument("--stages", type=int, default=2, help="NUTS stages, each adapting its mass to the last's draws")
    args = ap.parse_args(argv)

    import arviz as az
    import blackjax
    import jax
    import jax.numpy as jnp
    from blackjax.adaptation.step_size import dual_averaging_adaptation

    import latentforce

    latentforce.enable_x64()
    from nonlinear_calibration import Case, case_config, simulate

    from latentforce.inference import latent, particle_model, path_moves, pgas_start, smoother_move
    from latentforce.inference.latent import predicted_observations
    from latentforce.inference.path_moves import _regression, _value_gains
    from latentforce.io.config import config_from_dict

    T = args.T
    case = Case(order=args.order, k3=args.k3, sensors=args.sensors, noise=0.01, start="rest", T=T)
    y, truth, noise_sd, _ = simulate(case, 0)
    cfg = case_config(case, "pgas", 60)
    for sensor, sd in zip(cfg["sensors"], noise_sd):
        sensor["noise_std"] = float(sd)
    problem = config_from_dict(cfg)
    params = dict(problem.fixed)
    pm = particle_model.ParticleModel(problem.model, params, case.dt)
    tr = pm.transition(params["force_variance"], params["force_lengthscale"])
    y = jnp.asarray(y)
    mask = jnp.ones_like(y, dtype=bool)
    od = latent.observation_density(pm, y, mask)
    nl, nm, nfx, lay = pm.nl, pm.nm, pm.nfx, pm.latent_layout
    scale = jnp.sqrt(jnp.diagonal(od.Rinv, axis1=1, axis2=2))

    def obs_res(path):
        return ((od.y - predicted_observations(pm, path)) * scale).reshape(-1)

    def res_e(e):
        return obs_res(pm.path(latent.colour(tr, e.reshape(T, nl))))

    obj_e = jax.jit(lambda e: 0.5 * jnp.sum(e**2) + 0.5 * jnp.sum(res_e(e) ** 2))
    jac_e = jax.jit(jax.jacrev(res_e))

    def levenberg_marquardt(e, iters=60):
        # damped: the chains' paths are far from the mode, where plain Gauss-Newton can overshoot
        lam, f = 1e-3, float(obj_e(e))
        for _ in range(iters):
            r, J = res_e(e), jac_e(e)
            g = e + J.T @ r
            a = 1.0 + lam
            e_new = e - (g - J.T @ jnp.linalg.solve(a * jnp.eye(J.shape[0]) + J @ J.T, J @ g)) / a
            f_new = float(obj_e(e_new))
            if f_new < f:
                done = f - f_new < 1e-9 * max(1.0, abs(f))
                e, f, lam = e_new, f_new, max(lam / 3, 1e-9)
                if done:
                    break
            else:
                lam *= 10
                if lam > 1e8:
                    break
        return e, f

    # the mode: the smoother move's own centre (Gauss-Newton from the extended Kalman smoother)
    eks = jax.jit(lambda: pgas_start.extended_kalman_smoother(pm, tr, y, mask))()
    mode_path = jax.jit(lambda p: smoother_move.iterated_centre(pm, tr, od, p, iterations=12))(eks)
    mode = latent.whiten(tr, pm.latent(mode_path)).reshape(-1)
    f_mode = float(obj_e(mode))
    print(f"mode (Gauss-Newton from the extended Kalman smoother): -log p {f_mode:.3f} (+ const)")

    if args.modes:
        from latentforce.inference.pgas import run_pgas

        out = run_pgas(jax.random.key(3), problem.model, params, {}, y, mask, case.dt, iterations=600,
                       burn_in=300, chains=args.modes, max_time=1e9)  # fmt: skip
        print(f"pgas, {args.modes} chains, 300 + 600: max R-hat {out.diagnostics['convergence']['max_r_hat']:.2f}")
        for c in range(args.modes):
            e0 = latent.whiten(tr, pm.latent(jnp.asarray(out.trajectories[c, -1]))).reshape(-1)
            e, f = levenberg_marquardt(e0)
            print(
                f"chain {c}: -log p {float(obj_e(e0)):.1f} -> local mode {f:.3f}, "
                f"distance to the smoother's mode {float(jnp.linalg.norm(e - mode)):.2e} (whitened units)"
            )

    # the flat coordinates x = (w, the accelerometer's prediction, h) at every sample, the force solved
    rm = path_moves.ResidualMove(pm, T, 4, jnp.ones(nm))
    rows, cols = rm.rows, rm.cols
    b = np.setdiff1d(np.arange(nfx), cols)
    Af = tr.A[lay.force, lay.force]
    K = _value_gains(tr, lay.force, cols, b, T)
    idx = np.arange(nl)
    a1 = np.concatenate([idx[lay.force][cols], idx[lay.noise]])
    b1 = idx[lay.force][b]
    K1 = _regression(tr.Pinf, a1, b1)
    g0 = pm.latent(mode_path)
    xf0, w0 = g0[:, lay.force], g0[:, lay.noise]
    e0 = jnp.concatenate([xf0[:1], xf0[1:] - xf0[:-1] @ Af.T])
    h0 = e0[:, b] - jnp.einsum("tbu,tu->tb", K, e0[:, cols])
    h0 = h0.at[0].set(g0[0, b1] - K1 @ g0[0, a1])
    nS = len(rows)

    def build(x):
        X = x.reshape(T, nm + nS + len(b))
        w, target, h = X[:, :nm], X[:, nm : nm + nS], X[:, nm + nS :]

        def force_state(mech, target_t, K_t, h_t, pred):
            u = rm.Dinv @ (target_t - pm.offset(mech)[rows])
            return jnp.zeros(nfx).at[cols].set(u).at[b].set(pred[b] + K_t @ (u - pred[cols]) + h_t)

        mech1 = pm.mech0_mean + w[0]
        u1 = rm.Dinv @ (target[0] - pm.offset(mech1)[rows])
        xf1 = jnp.zeros(nfx).at[cols].set(u1).at[b].set(K1 @ jnp.concatenate([u1, w[0]]) + h[0])

        def step(carry, inp):
            mech, xf = carry
            target_n, K_n, h_n, w_n = inp
            mech_n = pm.phi(mech, xf) + w_n
            xf_n = force_state(mech_n, target_n, K_n, h_n, Af @ xf)
            return (mech_n, xf_n), jnp.concatenate([mech_n, xf_n])

        _, rest = jax.lax.scan(step, (mech1, xf1), (target[1:], K[1:], h[1:], w[1:]))
        return jnp.concatenate([jnp.concatenate([mech1, xf1])[None], rest])

    x0 = jnp.concatenate([w0, predicted_observations(pm, mode_path)[:, rows], h0], axis=1).reshape(-1)
    print(f"flat map: rebuilds the mode's path to {float(jnp.max(jnp.abs(build(x0) - mode_path))):.1e}")

    def res_path(path):
        return jnp.concatenate([latent.whiten(tr, pm.latent(path)).reshape(-1), obs_res(path)])

    obj_c = jax.jit(lambda p: 0.5 * jnp.sum(res_path(p.reshape(T, -1)) ** 2))
    obj_x = jax.jit(lambda x: 0.5 * jnp.sum(res_path(build(x)) ** 2))
    Je = np.asarray(jac_e(mode))
    Jc = np.asarray(jax.jit(jax.jacrev(lambda p: res_path(p.reshape(T, -1))))(mode_path.reshape(-1)))
    Jx = np.asarray(jax.jit(jax.jacrev(lambda x: res_path(build(x))))(x0))

    def inverse_root(H):
        # L^{-T} with L L^T = H, on the correlation scale: the flat coordinates mix units (w in m,
        # the prediction in m/s^2), so H's condition number is 1e18-1e24 and a jitter on H itself
        # would cap the wide directions' sd
        d = 1.0 / np.sqrt(np.diagonal(H))
        L = np.linalg.cholesky(H * d[:, None] * d[None, :])
        return d[:, None] * np.linalg.solve(L.T, np.eye(H.shape[0]))

    rng = np.random.default_rng(0)
    coords = (
        ("whitened latent", np.eye(mode.size) + Je.T @ Je, np.asarray(mode), obj_e),
        ("state path", Jc.T @ Jc, np.asarray(mode_path).reshape(-1), obj_c),
        ("flat", Jx.T @ Jx, np.asarray(x0), obj_x),
    )
    for name, H, xm, obj in coords:
        Lt_ = inverse_root(H)
        for frac in (1.0, 0.3):
            Z = rng.standard_normal((2000, xm.size))
            f = np.asarray(jax.vmap(obj)(jnp.asarray(xm + frac * Z @ Lt_.T))) - float(obj(xm))
            lw = -f + 0.5 * frac**2 * (Z**2).sum(1)
            print(
                f"Laplace draws, {name}, scale {frac}: -log p excess median {np.median(f):.1f} "
                f"(a Gaussian {frac**2 * xm.size / 2:.0f}), log-weight sd {lw.std():.1f}"
            )
    if not args.warmup:
        return 0

    n = x0.size
    Hx = coords[2][1]
    Lt = jnp.asarray(inverse_root(Hx))

    def log_density(z):
        return -obj_x(x0 + Lt @ z)

    da_init, da_update, da_final = dual_averaging_adaptation(0.8)
    kernel = blackjax.mcmc.nuts.build_kernel()

    @jax.jit
    def run(keys, z0, inv_mass):
        def chain(k, z):
            def warm_step(c, kk):
                st, da = c
                st, info = kernel(kk, st, log_density, jnp.exp(da.log_step_size), inv_mass, max_num_doublings=8)
                acc = jnp.where(jnp.isfinite(info.acceptance_rate), info.acceptance_rate, 0.0)
                return (st, da_update(da, acc)), None

            k1, k2 = jax.random.split(k)
            init = (blackjax.mcmc.nuts.init(z, log_density), da_init(0.3))
            (st, da), _ = jax.lax.scan(warm_step, init, jax.random.split(k1, args.warmup))
            h = da_final(da)

            def step(st, kk):
                st, info = kernel(kk, st, log_density, h, inv_mass, max_num_doublings=8)
                p = build(x0 + Lt @ st.position)
                return st, (p[:, 0], p[:, 2], info.num_integration_steps, st.position)

            return jax.lax.scan(step, st, jax.random.split(k2, args.draws))[1], h

        return jax.vmap(chain)(keys, z0)

    ti = np.linspace(0, T - 1, 24).astype(int)
    f_true, z_true = np.asarray(truth["force"]), np.asarray(truth["displacement"])

    def cover(a, t):
        m, s = a.mean((0, 1)), a.std((0, 1))
        return " / ".join(f"{100 * np.mean(np.abs(t - m) < k * s):.1f}" for k in (1, 2, 3))

    inv_mass, z0 = jnp.ones(n), jax.random.normal(jax.random.key(11), (4, n))
    for stage in range(1, args.stages + 1):
        t0 = time.perf_counter()
        (disp, force, steps, pos), h = run(jax.random.split(jax.random.key(5 + stage), 4), z0, inv_mass)
        disp, force = np.asarray(disp), np.asarray(force)
        rhat = max(float(az.rhat(a[:, :, i])) for a in (disp, force) for i in ti)
        ess = min(float(az.ess(a[:, :, i])) for a in (disp, force) for i in ti)
        print(
            f"NUTS stage {stage} ({args.warmup} + {args.draws} x 4): step {float(jnp.mean(h)):.3f}, "
            f"leapfrog steps {float(np.mean(steps)):.0f}, max R-hat {rhat:.3f}, min bulk ESS {ess:.0f}, "
            f"force inside ±1/2/3 sd {cover(force, f_true)} %, displacement {cover(disp, z_true)} %, "
            f"force NMSE {np.mean((force.mean((0, 1)) - f_true) ** 2) / f_true.var():.4f}, "
            f"{time.perf_counter() - t0:.0f} s (compile included)",
            flush=True,
        )
        lam, V = np.linalg.eigh(np.cov(np.asarray(pos).reshape(-1, n).T))
        wide = lam > 1.5
        top = np.round(lam[::-1][:4], 0)
        print(f"  draws' covariance in Laplace units: largest eigenvalues {top}, {wide.sum()} above 1.5")
        inv_mass = jnp.asarray(np.eye(n) + (V[:, wide] * (lam[wide] - 1.0)) @ V[:, wide].T)
        z0 = jnp.asarray(np.asarray(pos)[:, -1])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
