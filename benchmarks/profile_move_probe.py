r"""A profile move for the initial hysteretic force: is r0's ridge followed when the Gaussian is re-centred at each r0?

On the Bouc-Wen record with a Matérn-5/2 force and the default (wide) initial prior, ``pgas`` is slow in one
coordinate, the initial hysteretic force :math:`r_0` (posterior sd ~4 N); every move built so far proposes it
within 0.3-0.8 N of where it is, because the posterior of :math:`r_0` and the path together is a curved ridge
(docs/nonlinear.md, "Matérn-5/2: what still pins r0"). This probe measures a move that follows the ridge:

* :math:`r_0' = r_0 + s\,z`;
* :math:`c(r_0')`: Gauss-Newton on the path with :math:`r_0` pinned at :math:`r_0'` (each iteration the
  linearised smoother's mean, conditioned on the linear functional :math:`r_0` by its regression direction),
  started from a fixed centre, so a function of :math:`r_0'` alone;
* the path drawn from :math:`q_{c(r_0')}` conditioned on :math:`r_0 = r_0'` (a draw of the linearised
  posterior, moved along the regression direction: exact);
* accepted with :math:`\exp(L' - L)`, :math:`L = \log Z_c + \log q_c(r_0) + \log w_c(g)`, :math:`Z_c` the
  linearised marginal likelihood, :math:`q_c(r_0)` the linearised posterior's marginal density of :math:`r_0`,
  :math:`w_c = p(y\mid g)/\ell_c(g)` the smoother move's weight. Derivation: :math:`\pi(g)/q_c(g) = Z_c w_c(g)`
  and :math:`q_c(g \mid r_0) = q_c(g)/q_c(r_0)`, so the Metropolis-Hastings ratio of the proposal is
  :math:`\exp(L(r_0', g') - L(r_0, g))`.

Where the linearised posterior given :math:`r_0` is close to the true conditional (the virgin-start record's
smoother move accepted 94 %), :math:`L` is nearly the log marginal posterior of :math:`r_0` and the move a
random walk on that marginal. The probe runs a short ``pgas``, then from each chain's last path this move
alone (the rest of the path renewed by it too) and reports acceptance and r0's spread.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.inference import smoother_move as sm
from latentforce.inference.latent import colour

RESULTS = Path(__file__).resolve().parent / "results" / "profile_move_probe.md"


def r0_gradient(pm, tr, lin, r: int):
    """``(c, offset)``: r0 = offset + c . eps (exactly linear in the innovations)."""
    zero = jnp.zeros((lin.centre.shape[0], pm.nl))
    f = lambda e: sm.linear_path(pm, lin, colour(tr, e))[0, r]  # noqa: E731
    return jax.grad(f)(zero), f(zero)


def conditioned(pm, tr, od, prep: sm.Prepared, r: int, r0):
    """``(V, s2, m, c, off)``: regression direction of r0 under q, its variance, its mean, and its
    gradient/offset in the innovations."""
    lin, gains, eps_hat = prep
    c, off = r0_gradient(pm, tr, lin, r)
    zero = jnp.zeros_like(eps_hat)

    def pred(e):
        x = sm.linear_path(pm, lin, colour(tr, e))
        return jnp.einsum("tij,tj->ti", lin.H, x - lin.centre) * od.maskf

    Jc = pred(c) - pred(zero)
    sigma_c = c - (sm._smooth(pm, lin, gains, od.y + Jc)[0] - eps_hat)
    s2 = jnp.sum(c * sigma_c)
    return sigma_c / s2, s2, off + jnp.sum(c * eps_hat), c, off


def pinned_centre(pm, tr, od, start, r: int, r0, iterations: int):
    """Gauss-Newton with r0 pinned, from ``start``."""

    def one(cen, _):
        prep = sm.prepare(pm, tr, od, cen)
        V, s2, m, c, off = conditioned(pm, tr, od, prep, r, r0)
        eps = prep.eps_hat + V * (r0 - m)
        return sm.linear_path(pm, prep.lin, colour(tr, eps)), None

    cen, _ = jax.lax.scan(one, start, None, length=int(iterations))
    return cen


def point(key, pm, tr, od, start, r, r0, iterations, path=None):
    """``(L, path)`` at r0: a proposed point (path None: drawn) or the current one."""
    cen = pinned_centre(pm, tr, od, start, r, r0, iterations)
    prep = sm.prepare(pm, tr, od, cen)
    lin, gains, eps_hat = prep
    V, s2, m, c, off = conditioned(pm, tr, od, prep, r, r0)
    a, v = sm._filter_means(pm, lin, gains, od.y)
    logZ = sm._log_marginal(gains, v)
    logq = -0.5 * (jnp.log(2 * jnp.pi * s2) + (r0 - m) ** 2 / s2)
    if path is None:
        eps = sm._draw_eps(key, pm, tr, lin, gains, od, eps_hat)
        eps = eps + V * (r0 - off - jnp.sum(c * eps))
        g = colour(tr, eps)
        lw, path = sm.log_weight(pm, lin, od, g)
    else:
        lw = sm._log_weight(pm, lin, od, pm.latent(path), path)
    return logZ + logq + lw, path


def profile_move(key, pm, tr, od, start, path, r, n_steps, scale, iterations):
    L0, _ = point(None, pm, tr, od, start, r, path[0, r], iterations, path)

    def step(carry, k):
        L, x = carry
        k1, k2, k3 = jax.random.split(k, 3)
        r0p = x[0, r] + scale * jax.random.normal(k1)
        Lp, xp = point(k2, pm, tr, od, start, r, r0p, iterations)
        ok = jnp.isfinite(Lp) & (jnp.log(jax.random.uniform(k3)) < Lp - L)
        return (jnp.where(ok, Lp, L), jnp.where(ok, xp, x)), (ok, jnp.where(ok, xp, x)[0, r], Lp - L)

    _, out = jax.lax.scan(step, (L0, path), jax.random.split(key, n_steps))
    return out


def main(argv=None) -> int:
    """Short pgas on the Bouc-Wen Matérn-5/2 record, then the profile move from each chain's last path."""
    import latentforce

    latentforce.enable_x64()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from start_up_probe import bouc_wen_chains

    parser = argparse.ArgumentParser(description=main.__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--order", type=int, default=2)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--scales", default="1,3,6")
    parser.add_argument("--gn", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    paths, pm, tr, od = bouc_wen_chains(args.order, args.iterations, args.seed, "profile_move_probe")
    t_pgas = time.perf_counter() - t0
    r = 2 * pm.ndof
    start = sm.iterated_centre(pm, tr, od, jnp.asarray(paths[0, -1]))
    rows = []
    for scale in (float(s) for s in args.scales.split(",")):
        move = jax.jit(lambda k, p, s=scale: profile_move(k, pm, tr, od, start, p, r, args.steps, s, args.gn))
        for ch in range(paths.shape[0]):
            p0 = jnp.asarray(paths[ch, -1])
            t1 = time.perf_counter()
            ok, r0s, dL = jax.block_until_ready(move(jax.random.key(100 + ch), p0))
            dt = time.perf_counter() - t1
            r0s = np.asarray(r0s)
            rows.append((scale, ch, float(p0[0, r]), float(np.mean(ok)), float(np.std(r0s)), r0s.min(), r0s.max(), dt))
            print(rows[-1], flush=True)
    sd_post = float(np.std(paths[:, :, 0, r]))
    lines = [
        "# A profile move for the initial hysteretic force (benchmarks/profile_move_probe.py)",
        "",
        f"{time.strftime('%Y-%m-%dT%H:%M:%S')}; Bouc-Wen record of nonlinear_calibration.py --system bouc-wen "
        f"(seed {args.seed}), Matérn order index {args.order}, default initial prior; pgas {args.iterations} "
        f"iterations ({t_pgas:.0f} s), 4 chains; from each chain's last path {args.steps} profile-move steps "
        f"alone ({args.gn} Gauss-Newton iterations a point, started from chain 0's centre).",
        "",
        "| step sd (N) | chain | r0 at the start (N) | acceptance | sd of r0 over the steps (N) | min | max | s |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
        *(
            f"| {a:g} | {b} | {c:.2f} | {d:.3f} | {e:.2f} | {f:.2f} | {g:.2f} | {h:.1f} |"
            for a, b, c, d, e, f, g, h in rows
        ),
        "",
        f"sd of r0 over pgas's stored draws (all chains): {sd_post:.3g} N.",
        "",
        f"Total {time.perf_counter() - t0:.0f} s.",
    ]
    RESULTS.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
