r"""What pins the initial hysteretic force at Matérn-5/2 when the motion is held? (a probe)

``benchmarks/start_up_probe.py`` found the start-up move's coordinate, the initial hysteretic force
:math:`r_0` under the kinematic map (displacements and velocities held, the force's derivative
states following their filtering regression), 0.4-0.6 N wide at Matérn-5/2 against a posterior sd
of about 4 N. This probe asks whether a better rule for the force could free it.

At each chain's last path of a short ``pgas`` run on the Bouc-Wen record of
``benchmarks/nonlinear_calibration.py --system bouc-wen`` it builds one direction :math:`V` in the
latent :math:`g = (x_f, w)` as smooth as holding the motion allows: :math:`r_0` up by one newton,
the hysteretic force's change :math:`\Delta r_t` (the kinematic map's, to first order) taken up
by the force values exactly (:math:`\Delta u_t = \Delta r_t`, so the accelerations stay), the
force's derivative states given by the prior's *smoothing* regression on that value change (the
least-cost way, under the Matérn prior, for the force states to carry it), the displacements and
velocities held, and the within-step noise :math:`w` whatever that implies. It then evaluates the
exact log target (latent prior and observations, nothing linearised) along :math:`g + aV` on a
grid of :math:`a` and reports the conditional sd, and the sd each term alone would allow (from
its curvature at :math:`a = 0`): the force's innovations, the mechanical within-step noise, the
observations (the innovations whitened in the latent's order: the force's, then each within-step
noise given the ones before it). A step along a fixed :math:`V` is an exact Metropolis move for
any :math:`V`, so the conditional sd is what such a move could reach.

Usage::

    python benchmarks/start_up_direction_probe.py       # table to benchmarks/results/start_up_direction_probe.md
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

RESULTS = Path(__file__).resolve().parent / "results" / "start_up_direction_probe.md"


def _smoothing_regression(tr, lay, col: int, T: int) -> np.ndarray:
    """``(T * nfx, T)``: the force states' regression on the force values over the record under the
    stationary Matérn prior (dense; the probe's record is short)."""
    A = np.asarray(tr.A)[lay.force, lay.force]
    P = np.asarray(tr.Pinf)[lay.force, lay.force]
    n = A.shape[0]
    powers = [np.eye(n)]
    for _ in range(T - 1):
        powers.append(A @ powers[-1])
    C = np.zeros((T * n, T * n))
    for t in range(T):
        for s in range(t + 1):
            blk = powers[t - s] @ P
            C[t * n : (t + 1) * n, s * n : (s + 1) * n] = blk
            C[s * n : (s + 1) * n, t * n : (t + 1) * n] = blk.T
    u = np.arange(T) * n + col
    L = np.linalg.cholesky(C[np.ix_(u, u)] + 1e-10 * C[u[0], u[0]] * np.eye(T))
    return np.linalg.solve(L.T, np.linalg.solve(L, C[:, u].T)).T


def probe(order: int, iterations: int, seed: int) -> tuple[list[tuple], float]:
    import jax
    import jax.numpy as jnp
    from start_up_probe import bouc_wen_chains

    from latentforce.inference import latent, particle_model, path_moves

    paths, pm, tr, od = bouc_wen_chains(order, iterations, seed, "start_up_direction_probe")
    rm = path_moves.ResidualMove(pm, paths.shape[2], 16, jnp.sqrt(jnp.diagonal(tr.Q)[pm.latent_layout.noise]))
    T, lay, r = paths.shape[2], pm.latent_layout, 2 * pm.ndof  # r: the hysteretic force in the mechanical state
    j, s0 = rm.K * pm.nm + r, float(rm.scale_0[r])  # r0's coordinate in the moves' units (prior sds)
    col = int(np.asarray(rm.cols)[0])  # the force value among the force states
    reg = jnp.asarray(_smoothing_regression(tr, lay, col, T))
    kin = jnp.arange(pm.nm) < 2 * pm.ndof
    cP, cQ = particle_model._chol(tr.Pinf), particle_model._chol(tr.Q)

    def direction(centre):
        build = rm.builder(pm, od, tr, centre, kinematic=True)
        _, dpath = jax.jvp(lambda a: build(jnp.zeros(rm.dim).at[j].set(a / s0))[1], (0.0,), (1.0,))
        dxf = jnp.reshape(reg @ dpath[:, pm.nm + col], (T, pm.nfx))
        mech_c, xf_c = centre[:, pm.layout.mech], centre[:, pm.layout.force_states]

        def latent_at(d):
            xf = xf_c + d * dxf
            m1 = mech_c[0].at[r].add(d)

            def step(m, inp):
                x_prev, held = inp
                nxt = jnp.where(kin, held, pm.phi(m, x_prev))
                return nxt, nxt

            _, ms = jax.lax.scan(step, m1, (xf[:-1], mech_c[1:]))
            return pm.latent(jnp.concatenate([jnp.concatenate([m1[None], ms]), xf], axis=1))

        return jax.jvp(latent_at, (0.0,), (1.0,))[1]

    def terms(g):
        e = latent._whiten(tr, g, cP, cQ)
        noise = e[:, lay.noise]
        return jnp.stack(
            [
                -0.5 * jnp.sum(e[:, lay.force] ** 2),
                -0.5 * jnp.sum(noise[:, : pm.ndof] ** 2),  # displacements' within-step noise
                -0.5 * jnp.sum(noise[:, pm.ndof : 2 * pm.ndof] ** 2),  # velocities'
                -0.5 * jnp.sum(noise[:, 2 * pm.ndof :] ** 2),  # the hysteretic force's
                latent.observation_log_likelihood(pm, od, pm.path(g)),
            ]
        )

    grid = jnp.linspace(-30.0, 30.0, 241)

    @jax.jit
    def profile(path, V):
        g = pm.latent(path)
        return jax.vmap(lambda a: jnp.sum(terms(g + a * V)))(grid), jax.hessian(lambda a: terms(g + a * V))(0.0)

    def sd_of(lt):
        w = np.exp(np.asarray(lt) - np.max(lt))
        w /= w.sum()
        m = float(np.sum(w * grid))
        return float(np.sqrt(np.sum(w * (np.asarray(grid) - m) ** 2)))

    dirs = [direction(jnp.asarray(paths[c, -1])) for c in range(paths.shape[0])]
    rows = []
    for c in range(paths.shape[0]):
        lt, curv = profile(jnp.asarray(paths[c, -1]), dirs[c])
        lt_other, _ = profile(jnp.asarray(paths[c, -1]), dirs[(c + 1) % len(dirs)])
        per_term = [float(1.0 / np.sqrt(-x)) if x < 0 else float("inf") for x in np.asarray(curv)]
        rows.append((c, float(paths[c, -1, 0, r]), sd_of(lt), sd_of(lt_other), *per_term))
    return rows, float(np.std(paths[:, :, 0, r]))


def main(argv=None) -> int:
    import latentforce

    latentforce.enable_x64()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--order", type=int, default=2, help="Matérn order (0..3)")
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    rows, post_sd = probe(args.order, args.iterations, args.seed)
    lines = [
        "# What pins the initial hysteretic force when the motion is held (benchmarks/start_up_direction_probe.py)",
        "",
        f"{time.strftime('%Y-%m-%dT%H:%M:%S')}; Bouc-Wen record of nonlinear_calibration.py --system bouc-wen "
        f"(seed {args.seed}), Matérn-{2 * args.order + 1}/2; pgas {args.iterations} iterations, 4 chains; at each "
        "chain's last path the exact log target along the direction V (module doc: r0 up, the force taking up "
        "the change smoothly, the motion held) on a grid of +-30 N.",
        "",
        "| chain | r0 at the path (N) | conditional sd along V (N) | along the next chain's V (N) "
        "| sd allowed by: force innovations | displacements' within-step noise | velocities' within-step noise "
        "| hysteretic force's within-step noise | observations |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        lines.append("| " + " | ".join([str(row[0])] + [f"{x:.3g}" for x in row[1:]]) + " |")
    lines += [
        "",
        f"Posterior sd of r0 over the stored draws: {post_sd:.3g} N. The per-term sds are 1/sqrt of each "
        "term's curvature along V at the path (inf: flat or convex there); the terms are the latent's whitened "
        "innovations in its own order (the force's, then each within-step noise given the ones before it), so "
        "they add up to the prior's. The grid's step is 0.25 N.",
        "",
        f"Total {time.perf_counter() - t0:.0f} s.",
    ]
    text = "\n".join(lines) + "\n"
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
