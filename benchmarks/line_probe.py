r"""Probe (not a move of the sampler): Gibbs steps of the linearised model's posterior along its
regression lines, corrected to the target by Metropolis-Hastings.

Measured and not adopted (2026-12-01, ``benchmarks/results/line_probe.md``, docs/nonlinear.md
"A line move: measured, not adopted"). The move, as built and tested then:

**Why.** Some posteriors hold one or a few quantities that every other move renews slowly: the
initial hysteretic force of a Bouc-Wen record with a smooth force (the start-up move can step it
only by 0.4-0.6 N where the posterior is 4-5 N wide, because holding the motion at the samples
costs within-step noise: ``benchmarks/results/start_up_direction_probe.md``), the
displacement's constant of integration with acceleration and velocity measured. The smoother
move (:mod:`latentforce.inference.smoother_move`) proposes whole paths from the linearised
model's Gaussian :math:`q`, and a whole path is accepted only where :math:`q` fits the target
over the whole record. This move changes one scalar quantity at a time, moving the rest of the
path with it the way :math:`q` says they co-vary, so its acceptance depends on how well
:math:`q` fits along one line.

**The move.** In the whitened innovations :math:`\varepsilon` of the latent (prior
:math:`N(0, I)`), :math:`q = N(\hat\varepsilon, \Sigma)` with
:math:`\Sigma^{-1} = I + J^\top R^{-1} J`, :math:`J` the Jacobian of the expanded sensors'
prediction. Take a linear functional of the expanded path, :math:`\phi(\varepsilon) =
a^\top x^{\rm lin}_t(\varepsilon) = c^\top \varepsilon + {\rm const}` (a state, or a force, at
one time), and its regression direction :math:`V = \Sigma c / s^2`, :math:`s^2 = c^\top \Sigma
c` the variance of :math:`\phi` under :math:`q`. Write :math:`\varepsilon = V\phi +
\rho`; under :math:`q` the residual :math:`\rho` is independent of :math:`\phi`. A step keeps
:math:`\rho` and redraws :math:`\phi` by a Crank-Nicolson autoregression about its
:math:`q`-marginal :math:`N(\hat\phi, s^2)`:

.. math:: \phi' = \hat\phi + \sqrt{1-\beta^2}\,(\phi - \hat\phi) + \beta s z, \qquad
          \varepsilon' = \varepsilon + (\phi' - \phi) V, \quad z \sim N(0, 1).

It is a Gibbs step of :math:`q` along the line through :math:`\varepsilon` in direction
:math:`V` (for :math:`\beta = 1`; smaller :math:`\beta` an autoregression that keeps the same
line's conditional), reversible with respect to :math:`q` for *any* fixed :math:`V` (the line's
conditional under :math:`q` is a Gaussian in the step along it whatever the direction), so the
Metropolis-Hastings ratio for :math:`\pi = q\,w` is :math:`w(\varepsilon') / w(\varepsilon)`, the
smoother move's weight (:func:`~latentforce.inference.smoother_move.log_weight`): nothing
linearised in the target. :math:`V` only decides how far a step goes: with the exact
:math:`\Sigma c` the line's conditional under :math:`q` has the full marginal variance
:math:`s^2` (a direction estimated from draws of :math:`q` would carry their noise along the
other ~:math:`T n` dimensions and shrink it many times). :math:`\Sigma c` is computed exactly from
:math:`\Sigma = I - \Sigma J^\top R^{-1} J`: :math:`\Sigma c = c - [\hat\varepsilon(y + Jc) -
\hat\varepsilon(y)]`, two passes of the smoother's means (:func:`~latentforce.inference.smoother_move._smooth`)
with the gains the smoother move already has.

**Which lines.** Each step takes one functional at random (the key's draw, never the path's)
from :func:`line_functionals`: every mechanical state (displacement, velocity and internal
states of each DOF) and every force at :data:`LINE_TIMES` times spread over the record, the
first and last samples included (the record's start carries the initial state, its end the
least-determined slow content). For a linear system :math:`q = \pi` and every step is accepted
(``tests/test_line_move.py``), as for the smoother move.

Usage::

    PYTHONPATH=src python benchmarks/line_probe.py      # r0 lines on the Bouc-Wen record's chains
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from latentforce.inference import particle_model
from latentforce.inference import smoother_move as sm
from latentforce.inference.latent import ObservationDensity, colour, whiten

#: how many times over the record the move's functionals sit at (:func:`line_functionals`)
LINE_TIMES = 16

#: the steps' sizes along a line, used in turn (1: the line's Gibbs step for q)
LINE_BETAS = (1.0, 0.5)


def line_functionals(pm: particle_model.ParticleModel, T: int, n_times: int = LINE_TIMES):
    """``(times, weights)``: the move's linear functionals :math:`a^\\top x_t` of the path, every
    mechanical state and every force (its value, :meth:`~particle_model.ParticleModel._hold` at the
    step's start) at ``n_times`` times spread over ``0 .. T - 1``; ``times`` ``(F,)``,
    ``weights`` ``(F, n_state)``."""
    times = np.unique(np.round(np.linspace(0, T - 1, max(int(n_times), 1))).astype(int))
    # the forces' values in the force states (traced where the kernel's read-out depends on the numbers)
    Hf = jnp.atleast_2d(jax.jacfwd(lambda xf: pm._hold(xf, 0.0))(jnp.zeros(pm.nfx)))
    a = jnp.concatenate([jnp.eye(pm.n_state)[: pm.nm], jnp.concatenate([jnp.zeros((Hf.shape[0], pm.nm)), Hf], axis=1)])
    return np.repeat(times, a.shape[0]).astype(np.int32), jnp.tile(a, (times.size, 1))


def _prediction(pm, lin: sm.Linearisation, od: ObservationDensity, tr, eps) -> Float[Array, "T d"]:
    """The expanded sensors' prediction less its value at the centre, :math:`H (x^{\\rm lin} - \\bar x)`
    (observed channels; affine in ``eps``)."""
    x = sm.linear_path(pm, lin, colour(tr, eps))
    return jnp.einsum("tij,tj->ti", lin.H, x - lin.centre) * od.maskf


def directions(pm, tr, od: ObservationDensity, prepared: sm.Prepared, t, a):
    """``(c, V, s2)`` of the functional :math:`a^\\top x^{\\rm lin}_t` (module doc): its gradient in the
    innovations, its exact regression direction :math:`\\Sigma c / s^2` under the linearised
    posterior, and its variance there."""
    lin, gains, eps_hat = prepared
    zero = jnp.zeros_like(eps_hat)
    c = jax.grad(lambda e: jnp.dot(a, sm.linear_path(pm, lin, colour(tr, e))[t]))(zero)
    Jc = _prediction(pm, lin, od, tr, c) - _prediction(pm, lin, od, tr, zero)
    sigma_c = c - (sm._smooth(pm, lin, gains, od.y + Jc)[0] - eps_hat)
    s2 = jnp.sum(c * sigma_c)
    return c, sigma_c / s2, s2


def line_move(
    key: Array,
    pm: particle_model.ParticleModel,
    tr: particle_model.Transition,
    od: ObservationDensity,
    prepared: sm.Prepared,
    path: Float[Array, "T n"],
    n_steps: int,
    functionals: tuple[Int[Array, " F"], Float[Array, "F n"]],
    betas=LINE_BETAS,
) -> tuple[Float[Array, "T n"], Float[Array, " k"]]:
    """``n_steps`` Metropolis-Hastings steps along regression lines (module doc), each on a functional
    drawn from ``functionals`` (:func:`line_functionals`) with ``key``; ``prepared`` the linearised
    model about the chain's centre (:func:`~latentforce.inference.smoother_move.prepare`). Returns the
    new path and each step's acceptance (bool)."""
    times, weights = (jnp.asarray(f) for f in functionals)
    k_pick, k_z, k_acc = jax.random.split(key, 3)
    pick = jax.random.randint(k_pick, (int(n_steps),), 0, times.shape[0])
    cs, Vs, s2s = jax.vmap(lambda t, a: directions(pm, tr, od, prepared, t, a))(times[pick], weights[pick])
    z = jax.random.normal(k_z, (int(n_steps),))
    beta = jnp.asarray([float(betas[j % len(betas)]) for j in range(int(n_steps))])
    logu = jnp.log(jax.random.uniform(k_acc, (int(n_steps),)))
    lin, _, eps_hat = prepared
    g_cur = pm.latent(path)
    lw_cur = sm._log_weight(pm, lin, od, g_cur, path)

    def _step(carry, inp):
        lw, x, eps = carry
        c, V, s2, z_j, b, lu = inp
        phi, phi_hat = jnp.sum(c * eps), jnp.sum(c * eps_hat)
        phi_new = phi_hat + jnp.sqrt(1.0 - b**2) * (phi - phi_hat) + b * jnp.sqrt(jnp.maximum(s2, 0.0)) * z_j
        eps_p = eps + (phi_new - phi) * V
        lw_p, x_p = sm.log_weight(pm, lin, od, colour(tr, eps_p))
        ok = jnp.isfinite(lw_p) & (s2 > 0.0) & (lu < lw_p - lw)
        return (jnp.where(ok, lw_p, lw), jnp.where(ok, x_p, x), jnp.where(ok, eps_p, eps)), ok

    (_, out, _), acc = jax.lax.scan(_step, (lw_cur, path, whiten(tr, g_cur)), (cs, Vs, s2s, z, beta, logu))
    return out, acc


RESULTS = Path(__file__).resolve().parent / "results" / "line_probe.md"


def main(argv=None) -> int:
    """At each chain's last path of a short ``pgas`` run on the Bouc-Wen record (Matérn-5/2), 64 line
    steps along the initial hysteretic force's line alone: their acceptance and how far r0 goes."""
    import latentforce

    latentforce.enable_x64()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from start_up_probe import bouc_wen_chains

    parser = argparse.ArgumentParser(description=main.__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    paths, pm, tr, od = bouc_wen_chains(2, args.iterations, args.seed, "line_probe")
    r = 2 * pm.ndof
    prep = sm.prepare(pm, tr, od, sm.iterated_centre(pm, tr, od, jnp.asarray(paths[0, -1])))
    r0_line = (np.zeros(1, np.int32), jnp.eye(pm.n_state)[r][None])
    move = jax.jit(lambda k, p: line_move(k, pm, tr, od, prep, p, 64, r0_line))
    rows = []
    for c in range(paths.shape[0]):
        p0 = jnp.asarray(paths[c, -1])
        p1, acc = move(jax.random.key(100 + c), p0)
        rows.append((c, float(p0[0, r]), float(np.mean(np.asarray(acc))), float(p1[0, r])))
    lines = [
        "# Line moves on the Bouc-Wen record's initial hysteretic force (benchmarks/line_probe.py)",
        "",
        f"{time.strftime('%Y-%m-%dT%H:%M:%S')}; Bouc-Wen record of nonlinear_calibration.py --system bouc-wen "
        f"(seed {args.seed}), Matérn-5/2; pgas {args.iterations} iterations, 4 chains; at each chain's last path "
        "64 steps along r0's regression line, about the centre of chain 0's path (Gauss-Newton).",
        "",
        "| chain | r0 at the path (N) | acceptance | r0 after 64 steps (N) |",
        "|---:|---:|---:|---:|",
        *(f"| {c} | {a:.2f} | {b:.3f} | {d:.2f} |" for c, a, b, d in rows),
        "",
        f"Posterior sd of r0 over the stored draws: {float(np.std(paths[:, :, 0, r])):.3g} N (the start-up "
        "move's steps: 0.4-0.6 N wide, `start_up_direction_probe.md`).",
        "",
        f"Total {time.perf_counter() - t0:.0f} s.",
    ]
    RESULTS.write_text("\n".join(lines) + "\n" + SAMPLER_RUNS)
    print("\n".join(lines))
    return 0


#: the move wired into the Gibbs block (a hook: after the smoother move, about its expansion), measured
#: 2026-12-01 on the 2-core machine, one run each, 180 s cap, nothing else running
SAMPLER_RUNS = """
## In the sampler (2026-12-01)

The move wired into `pgas`'s Gibbs block right after the smoother move, about the same expansion (a
hook on the block; each step on a functional drawn from `line_functionals`: every mechanical state and
the force at 16 times), through `estimate.run` on the `nonlinear_calibration.py` records, 180 s cap,
one run each (a time-capped run's R-hat scatters by ~0.1-0.2 from run to run on these records):

| record | line steps a block | max R-hat | min bulk ESS | line-move acceptance |
|---|---|---:|---:|---:|
| Bouc-Wen, Matérn-5/2, acc + disp, T = 450 | none (the default) | 1.348 | 10 | – |
| | 8 | 1.252 | 12 | 0.85-0.92 |
| | 32 | 1.163 | 17 | 0.90-0.92 |
| | 8, functionals at the first and last sample only | 1.413 | 9 | 0.70-0.78 |
| Duffing k3 = 4e5, Matérn-5/2, acc + vel, moving start, T = 256 | none | 1.053 | 80 | – |
| | 8 | 1.056 | 82 | 0.53-0.58 |
| Duffing k3 = 4e4, Matérn-3/2, acc, T = 256 | none | 1.051 | 74 | – |
| | 8 | 1.068 | 67 | 0.15-0.17 |

The worst quantities stayed the Bouc-Wen record's first 0.05 s (force, hysteretic force). Not adopted.
"""


if __name__ == "__main__":
    sys.exit(main())
