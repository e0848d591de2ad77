r"""Virtual sensors (``[[outputs]]``): posterior of linear combinations of the states.

An output is

.. math:: o_t = c_z^T z_t + c_v^T \dot z_t + c_a^T \ddot z_t + c_u^T u_t,

with coefficient lists on the displacement, velocity, acceleration (one per
DOF) and the latent forces (one per force); a missing list is zero. The
acceleration is the model's: :math:`\ddot z = M^{-1}(B u - h(z, \dot z))`.
For a linear system it is the velocity block of the drift, a linear
function of the augmented state (force feed-through included, as for an
accelerometer, Eq. 23b of ISMA 2018), so every output is
:math:`o_t = G x_t` with a fixed matrix :math:`G` (:func:`output_matrix`) and

* under ``kalman`` its posterior is exact:
  :math:`E[o_t] = G m_t`, :math:`\operatorname{Var}[o_t] = \operatorname{diag}(G P_t G^T)`
  from the smoothed mean and *full* covariance :math:`P_t` (cross-covariances
  between displacement, velocity and force states included);
* under ``kalman-mcmc``/``kalman-nuts`` it is the mixture over parameter
  draws: :math:`E[o_t] = \overline{G_\theta m_t(\theta)}` and
  :math:`\operatorname{Var}[o_t] = \overline{\operatorname{diag}(G_\theta P_t(\theta) G_\theta^T)}
  + \operatorname{Var}_\theta[G_\theta m_t(\theta)]` (:mod:`latentforce.inference.mixture`);
* under ``pgas`` it is evaluated on each sampled path (any system, the
  acceleration from the system's own equation of motion) and summarised
  by the sample mean and standard deviation (:func:`path_outputs`);
* under ``ekf``/``ukf`` it is the output function :math:`o(x)` of one state
  (:func:`output_function`, any system) taken through the method's own
  Gaussian transform of the smoothed :math:`N(m_t, P_t)` (linearised at
  :math:`m_t`, or by the cubature points: ``inference.gaussian``), exact for
  a linear system, where :math:`o(x) = G x`; with inferred parameters, mixed
  over the draws as above.

Outputs are reported beside the states: ``NAME_mean``/``NAME_sd`` in
``summary.csv`` and ``posterior.nc``, sampled paths ``NAME`` there under the
samplers, and a figure ``figures/output_NAME.png``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.compile import jit, numbers
from latentforce.models import LatentForceModel

__all__ = ["OutputSpec", "gaussian_moments", "output_function", "output_matrix", "path_outputs", "sample_moments"]


class OutputSpec(NamedTuple):
    """One ``[[outputs]]`` table: a name, a unit label and coefficient lists (``None`` = zero)."""

    name: str
    unit: str = ""
    displacement: tuple[float, ...] | None = None
    velocity: tuple[float, ...] | None = None
    acceleration: tuple[float, ...] | None = None
    force: tuple[float, ...] | None = None


def _coefficients(spec: OutputSpec, kind: str, width: int) -> np.ndarray:
    c = getattr(spec, kind)
    return np.zeros(width) if c is None else np.asarray(c, dtype=float)


def _coefficient_matrices(outputs: Sequence[OutputSpec], nd: int, nf: int) -> tuple[np.ndarray, ...]:
    """The outputs' coefficients as rows ``(k, width)``: displacement, velocity, acceleration (``nd``
    wide each) and force (``nf`` wide)."""
    return tuple(
        np.stack([_coefficients(s, kind, width) for s in outputs])
        for kind, width in (("displacement", nd), ("velocity", nd), ("acceleration", nd), ("force", nf))
    )


def output_matrix(model: LatentForceModel, outputs: Sequence[OutputSpec], params: dict) -> Float[Array, "k n"]:
    r""":math:`G` with :math:`o_t = G x_t` for a linear system (module doc).

    The acceleration rows are the velocity block of the continuous drift
    :math:`F` (``model.continuous``), the force rows pick :math:`u = H_u x`.
    """
    F, _ = model.continuous(params)
    nd, L = model.ndof, model.layout
    Hu = model.force_matrix()
    rows = []
    for spec in outputs:
        g = jnp.zeros(model.n_state)
        g = g.at[L.displacement].add(jnp.asarray(_coefficients(spec, "displacement", nd)))
        g = g.at[L.velocity].add(jnp.asarray(_coefficients(spec, "velocity", nd)))
        g = g + jnp.asarray(_coefficients(spec, "acceleration", nd)) @ F[L.velocity]
        g = g + jnp.asarray(_coefficients(spec, "force", model.nforce)) @ Hu
        rows.append(g)
    return jnp.stack(rows)


def output_function(model: LatentForceModel, outputs: Sequence[OutputSpec], params: dict):
    r"""``o(x)``: the outputs ``(k,)`` of one augmented state ``x`` (``(n_state,)``), any system: the
    acceleration from the system's equation of motion at ``params`` (module doc). For a linear
    system :math:`o(x) = G x` (:func:`output_matrix`)."""
    L = model.layout
    cz, cv, ca, cu = _coefficient_matrices(outputs, model.ndof, model.nforce)
    Hu = model.force_matrix()
    with_acceleration = bool(np.any(ca))

    def fn(x):
        z, v, r = L.split_mech(x[L.mech])
        u = Hu @ x
        out = cz @ z + cv @ v + cu @ u
        if with_acceleration:
            out = out + ca @ model.system.acceleration(params, z, v, u, r)
        return out

    return fn


def gaussian_moments(
    G: Float[Array, "k n"], means: Float[Array, "T n"], covs: Float[Array, "T n n"]
) -> tuple[np.ndarray, np.ndarray]:
    r"""Mean :math:`G m_t` and sd :math:`\sqrt{\operatorname{diag}(G P_t G^T)}`, ``(T, k)`` each."""
    mean = jnp.asarray(means) @ G.T
    var = jnp.einsum("ki,tij,kj->tk", G, jnp.asarray(covs), G)
    return np.asarray(mean), np.sqrt(np.clip(np.asarray(var), 0.0, None))


def path_outputs(
    model: LatentForceModel,
    outputs: Sequence[OutputSpec],
    params: dict,
    z: Float[Array, "... T nd"],
    v: Float[Array, "... T nd"],
    u: Float[Array, "... T nf"],
    draw_params: dict | None = None,
    r: Float[Array, "... T ni"] | None = None,
) -> np.ndarray:
    """The outputs ``(..., T, k)`` of sampled paths of displacement, velocity and force,
    the acceleration from the system's equation of motion (any system). ``draw_params``:
    sampled parameters, ``name -> (...)`` one value per path (the leading axes of ``z``), which
    replace those in ``params`` path by path (the equation of motion of each draw's own system).
    ``r``: the paths of the system's internal states (a Bouc-Wen system's hysteretic force)."""
    z, v, u = (jnp.asarray(a, dtype=float) for a in (z, v, u))
    nd, nf, ni = model.ndof, model.nforce, model.layout.n_internal
    r = jnp.zeros((*z.shape[:-1], ni)) if r is None else jnp.asarray(r, dtype=float)
    cz, cv, ca, cu = (jnp.asarray(c) for c in _coefficient_matrices(outputs, nd, nf))
    out = z @ cz.T + v @ cv.T + u @ cu.T
    if np.any(np.asarray(ca)):
        lead = z.shape[:-1]
        n_rows = int(np.prod(lead))
        rows = (z.reshape(n_rows, nd), v.reshape(n_rows, nd), u.reshape(n_rows, nf), r.reshape(n_rows, ni))
        if draw_params:  # every time of a path at its draw's parameters
            per_row = {
                n: jnp.broadcast_to(jnp.asarray(d, dtype=float)[..., None], lead).reshape(-1)
                for n, d in draw_params.items()
            }
            a = _accelerations_per_row(numbers(params), per_row, *rows, system=model.system).reshape(*lead, nd)
        else:
            a = _accelerations(numbers(params), *rows, system=model.system).reshape(*lead, nd)
        out = out + a @ ca.T
    return np.asarray(out)


@functools.partial(jit, static_argnames=("system",))
def _accelerations(params, z, v, u, r, *, system):
    return jax.vmap(lambda zz, vv, uu, rr: system.acceleration(params, zz, vv, uu, rr))(z, v, u, r)


@functools.partial(jit, static_argnames=("system",))
def _accelerations_per_row(params, per_row, z, v, u, r, *, system):
    return jax.vmap(lambda pr, zz, vv, uu, rr: system.acceleration({**params, **pr}, zz, vv, uu, rr))(
        per_row, z, v, u, r
    )


def sample_moments(paths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and sd over ``(chains, draws)`` of paths ``(chains, draws, T, k)``."""
    flat = np.asarray(paths).reshape(-1, *np.shape(paths)[2:])
    sd = flat.std(axis=0, ddof=1) if flat.shape[0] > 1 else np.zeros(flat.shape[1:])
    return flat.mean(axis=0), sd


def split(
    outputs: Sequence[OutputSpec], mean: np.ndarray, sd: np.ndarray, paths: np.ndarray | None = None
) -> tuple[dict, dict, dict]:
    """Per-output ``(T, 1)`` means and sds and ``(chains, draws, T, 1)`` paths from ``(..., k)`` arrays."""
    means = {s.name: np.asarray(mean)[:, i : i + 1] for i, s in enumerate(outputs)}
    sds = {s.name: np.asarray(sd)[:, i : i + 1] for i, s in enumerate(outputs)}
    sampled = {} if paths is None else {s.name: np.asarray(paths)[..., i : i + 1] for i, s in enumerate(outputs)}
    return means, sds, sampled


def units(outputs: Sequence[OutputSpec]) -> dict[str, str]:
    """``{name: unit}`` of the outputs, as the result records them."""
    return {s.name: s.unit for s in outputs}
