r"""Probe (not a move of the sampler): Crank-Nicolson steps about the Gaussian of the *current* path.

Measured and not adopted (2026-11-29, ``benchmarks/results/recentred_probe.md``, ``docs/nonlinear.md``
"A re-centred smoother move: measured, not adopted"). The move, as built and tested then:

The smoother move (:mod:`latentforce.inference.smoother_move`) draws from the linearised
model's smoother about a centre path that is fixed after the burn-in. With acceleration alone
on a stiffening structure that Gaussian fits the posterior only near its centre: the curvature
along the path's slow displacement content changes by orders of magnitude from one posterior
draw to the next (``benchmarks/results/whitened_nuts_probe.md``), so only its smallest
Crank-Nicolson steps pass, and chains that sit in different stretches of that slow content stay
there. The probe's move expands the model about the chain's *own* path at every step instead.

In the whitened innovations :math:`\varepsilon` of the latent (prior :math:`N(0, I)`) let
:math:`q_x = N(\hat\varepsilon_x, \Sigma_x)` be the linearised model's posterior about the path
:math:`x` (``smoother_move.linearise`` there): :math:`\Sigma_x^{-1} = I + J_x^\top R^{-1} J_x`,
:math:`J_x` the Jacobian of the expanded sensors' prediction in :math:`\varepsilon`, and
:math:`\hat\varepsilon_x` one Gauss-Newton step from :math:`\varepsilon`. The proposal is the
Crank-Nicolson autoregression about it,

.. math:: \varepsilon' = \hat\varepsilon_x + \rho\,(\varepsilon - \hat\varepsilon_x)
          + \beta\,(\varepsilon^q - \hat\varepsilon_x), \qquad
          \varepsilon^q \sim q_x,\ \rho = \sqrt{1 - \beta^2},

a Gaussian :math:`N(\hat\varepsilon_x + \rho(\varepsilon - \hat\varepsilon_x), \beta^2 \Sigma_x)`.
Its mean is :math:`\varepsilon + (1 - \rho)\,\Sigma_x \nabla \log \pi(\varepsilon)` under the
Gauss-Newton expansion, so for small :math:`\beta` this is the simplified manifold MALA of
Girolami & Calderhead (2011) with the Gauss-Newton (Fisher) metric and step
:math:`\approx \beta^2`. Because the Gaussian now depends on where the chain is, the reverse
proposal is not the forward one and the Metropolis-Hastings ratio carries both:

.. math:: \log r = \log\pi(\varepsilon') - \log\pi(\varepsilon)
          + \log N(\varepsilon;\, m_{x'}(\varepsilon'), \beta^2\Sigma_{x'})
          - \log N(\varepsilon';\, m_x(\varepsilon), \beta^2\Sigma_x),

:math:`\log\pi(\varepsilon) = -\tfrac12|\varepsilon|^2 + \log p(y \mid \mathrm{path})` exactly
(nothing linearised). The quadratic forms are :math:`|\delta|^2 + |R^{-1/2} J_x \delta|^2`
(:math:`J_x\delta` by one pass of the expanded model), and
:math:`\log|\Sigma_x^{-1}| = \sum_t \log|S_t| - \log|R|` from the expanded model's innovation
covariances, the :math:`R` term the same at both ends. For a linear system every expansion is
the same exact one, the two Gaussian terms cancel against the target's and every step is
accepted (``tests/test_recentred_move.py``); on a nonlinear one the move is exact by the ratio
(measured: on the small Duffing below its chains' per-time sd agree with NUTS's to 8 %).

Cost per step: one expansion with its covariance recursion and three smoothing passes more than
a fixed-centre step. The step sizes cycle through :data:`BETAS`.

Usage::

    PYTHONPATH=src python benchmarks/recentred_probe.py small      # vs NUTS and the fixed-centre move
    PYTHONPATH=src python benchmarks/recentred_probe.py scan --order 1 --k3 4e4   # acceptance per beta
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.inference import smoother_move as sm
from latentforce.inference.latent import ObservationDensity, colour, observation_log_likelihood, whiten

RESULTS = Path(__file__).resolve().parent / "results" / "recentred_probe.md"

#: the steps' sizes, one step each in turn
BETAS = (0.4, 0.2, 0.1)


class _Local(NamedTuple):
    """The Gaussian :math:`q_x` about a path: its expansion, covariance recursion and mean."""

    lin: sm.Linearisation
    gains: sm._Gains
    eps_hat: Float[Array, "T nl"]
    logdet: Float[Array, ""]  # sum_t log|S_t|: log|Sigma_x^-1| + log|R| (module doc)


def _local(pm, tr, od: ObservationDensity, path) -> _Local:
    lin = sm.linearise(pm, tr, path)
    gains = sm._gains(pm, tr, lin, od)
    return _Local(lin, gains, sm._smooth(pm, lin, gains, od.y)[0], jnp.sum(gains.logdet))


def _precision_quad(pm, tr, od: ObservationDensity, loc: _Local, delta) -> Float[Array, ""]:
    r""":math:`\delta^\top \Sigma_x^{-1} \delta = |\delta|^2 + |R^{-1/2} J_x \delta|^2` (module doc)."""
    g = colour(tr, delta)
    dx = sm.linear_path(pm, loc.lin, g) - sm.linear_path(pm, loc.lin, jnp.zeros_like(g))
    r = jnp.einsum("tij,tj->ti", loc.lin.H, dx) * od.maskf
    return jnp.sum(delta**2) + jnp.einsum("ti,tij,tj->", r, od.Rinv, r)


def recentred_move(
    key, pm, tr, od: ObservationDensity, path: Float[Array, "T n"], n_steps: int, betas=BETAS
) -> tuple[Float[Array, "T n"], Float[Array, " k"]]:
    r"""``n_steps`` Metropolis-Hastings steps about the Gaussian of the current path (module doc).

    Step ``j`` has size :math:`\beta_j` = ``betas[j % len(betas)]``. Returns the new path (the
    input bit-for-bit where nothing was accepted) and each step's acceptance (bool).
    """
    eps0 = whiten(tr, pm.latent(path))
    lp0 = -0.5 * jnp.sum(eps0**2) + observation_log_likelihood(pm, od, path)
    beta = jnp.asarray([float(betas[j % len(betas)]) for j in range(int(n_steps))])
    keys = jax.random.split(key, int(n_steps))

    def _step(carry, inp):
        eps, x, lp, loc = carry
        k, b = inp
        k_draw, k_acc = jax.random.split(k)
        rho = jnp.sqrt(1.0 - b**2)
        d = sm._draw_eps(k_draw, pm, tr, loc.lin, loc.gains, od, loc.eps_hat)
        eps_p = loc.eps_hat + rho * (eps - loc.eps_hat) + b * (d - loc.eps_hat)
        x_p = pm.path(colour(tr, eps_p))
        lp_p = -0.5 * jnp.sum(eps_p**2) + observation_log_likelihood(pm, od, x_p)
        loc_p = _local(pm, tr, od, x_p)
        fwd = -0.5 * _precision_quad(pm, tr, od, loc, d - loc.eps_hat) + 0.5 * loc.logdet
        back = eps - loc_p.eps_hat - rho * (eps_p - loc_p.eps_hat)
        rev = -0.5 * _precision_quad(pm, tr, od, loc_p, back) / b**2 + 0.5 * loc_p.logdet
        log_r = lp_p - lp + rev - fwd
        ok = jnp.isfinite(log_r) & (jnp.log(jax.random.uniform(k_acc)) < log_r)
        new = jax.tree.map(lambda a, o: jnp.where(ok, a, o), (eps_p, x_p, lp_p, loc_p), (eps, x, lp, loc))
        return new, ok

    (_, out, _, _), acc = jax.lax.scan(_step, (eps0, path, lp0, _local(pm, tr, od, path)), (keys, beta))
    return out, acc


# ----- the measurements ---------------------------------------------------------------------------


def _small_record(order: int):
    """The acceleration-only Duffing of ``tests/test_smoother_move.py`` (T = 40, k3 = 2e3)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_smoother_move import _duffing

    return _duffing(order, sensors=("acceleration",), T=40, k3=2e3)


def small(order: int, chains: int = 1000) -> list[str]:
    """Per-time displacement sd: NUTS (blackjax, 4 chains x 3000 draws) against ``chains`` chains of
    the fixed-centre smoother move and of this move, from draws of the fixed-centre proposal."""
    import blackjax

    from latentforce.compile import jit
    from latentforce.inference import latent, pgas_start

    pm, tr, y, mask = _small_record(order)
    od = latent.observation_density(pm, y, mask)
    eks = pgas_start.extended_kalman_smoother(pm, tr, y, mask)
    centre = sm.iterated_centre(pm, tr, od, eks)
    idx = [0, 2, 4, 10, 20, 39]
    lines = []

    def sd_of(x):
        return np.round(np.asarray(x.std(0))[idx, 0], 4).tolist()

    fixed = jit(
        lambda ks, xs, m: jax.vmap(lambda k, x: sm.smoother_move(k, pm, tr, od, centre, x, m, betas=(1.0, 0.5, 0.2)))(
            ks, xs
        ),
        static_argnums=2,
    )
    move = jit(lambda ks, xs, m: jax.vmap(lambda k, x: recentred_move(k, pm, tr, od, x, m))(ks, xs), static_argnums=2)
    start = jax.vmap(pm.path)(sm.proposal_draws(jax.random.key(0), pm, tr, od, centre, chains))
    a = b = start
    for i in range(6):
        a, _ = fixed(jax.random.split(jax.random.key(10 + i), chains), a, 500)
        lines.append(f"fixed-centre move, {500 * (i + 1)} steps: {sd_of(a)}")
    for i in range(4):
        b, _ = move(jax.random.split(jax.random.key(20 + i), chains), b, 50)
        lines.append(f"re-centred move, {50 * (i + 1)} steps: {sd_of(b)}")
    e0 = whiten(tr, pm.latent(eks))

    def logp(e):
        e = e.reshape(e0.shape)
        return -0.5 * jnp.sum(e**2) + observation_log_likelihood(pm, od, pm.path(colour(tr, e)))

    zs = []
    for c in range(4):
        key = jax.random.key(100 + c)
        init = e0.reshape(-1) + 0.1 * jax.random.normal(key, (e0.size,))
        adapt = blackjax.window_adaptation(blackjax.nuts, logp)
        (st, params), _ = jax.jit(lambda k, x: adapt.run(k, x, num_steps=1500))(jax.random.fold_in(key, 1), init)
        kernel = blackjax.nuts(logp, **params).step

        def one(s, k):
            s, _ = kernel(k, s)
            return s, pm.path(colour(tr, s.position.reshape(e0.shape)))

        _, x = jax.jit(lambda s, ks: jax.lax.scan(one, s, ks))(st, jax.random.split(jax.random.fold_in(key, 2), 3000))
        zs.append(x)
    lines.append(f"NUTS, 4 x 3000 draws: {sd_of(jnp.concatenate(zs))}")
    return lines


def scan(order: int, k3: float) -> list[str]:
    """Acceptance per beta on ``nonlinear_calibration.py``'s acceleration-only record (T = 256)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import nonlinear_calibration as nc

    from latentforce.compile import jit
    from latentforce.estimate_particles import _mechanical_initial
    from latentforce.inference import latent, particle_model, pgas_start
    from latentforce.io.config import config_from_dict

    case = nc.Case(order=order, k3=k3, sensors="acc", noise=0.01, start="rest", T=256)
    y, _, noise_sd, _ = nc.simulate(case, 0)
    cfg = nc.case_config(case, "pgas", 60.0)
    for sensor, sd in zip(cfg["sensors"], noise_sd):
        sensor["noise_std"] = float(sd)
    problem = config_from_dict(cfg, source="probe")
    params = dict(problem.fixed)
    pm = particle_model.ParticleModel(problem.model, params, case.dt, "rk4", _mechanical_initial(problem, params))
    tr = pm.transition(params["force_variance"], params["force_lengthscale"])
    y, mask = jnp.asarray(y), jnp.ones(y.shape, bool)
    od = latent.observation_density(pm, y, mask)
    centre = sm.iterated_centre(pm, tr, od, pgas_start.extended_kalman_smoother(pm, tr, y, mask))
    move = jit(
        lambda ks, xs, betas: jax.vmap(lambda k, x: recentred_move(k, pm, tr, od, x, len(betas), betas=betas))(ks, xs),
        static_argnums=2,
    )
    x, _ = move(jax.random.split(jax.random.key(0), 4), jnp.broadcast_to(centre, (4,) + centre.shape), (0.05,) * 100)
    out = []
    for b in (0.02, 0.05, 0.1, 0.2, 0.3):
        _, acc = move(jax.random.split(jax.random.key(int(b * 1000)), 4), x, (b,) * 40)
        out.append(f"Matérn-{2 * order + 1}/2, k3 = {k3:g}: beta {b}: acceptance {float(acc.mean()):.3f}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=("small", "scan"))
    ap.add_argument("--order", type=int, default=1)
    ap.add_argument("--k3", type=float, default=4e4)
    args = ap.parse_args(argv)
    import latentforce

    latentforce.enable_x64()
    t0 = time.perf_counter()
    lines = small(args.order) if args.mode == "small" else scan(args.order, args.k3)
    text = "\n".join(f"- {line}" for line in lines) + f"\n\n({args.mode}, {time.perf_counter() - t0:.0f} s)\n"
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
