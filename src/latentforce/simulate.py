r"""Simulate a structure's response to a latent force: the truth for demos and tests.

The force is either a sample of the model's GP (drawn exactly on a fine
grid from the kernel's discrete transition, ``substeps`` points per
sample) or a given function of time. The equations of motion
:math:`M\ddot z + h(z, \dot z) = B u` are integrated with classical RK4 on
that fine grid, the force linearly interpolated within each sub-step. The
acceleration is evaluated from the equation of motion at the sample times,
so measured accelerations are consistent with the states.

Numerics only: files are written by :mod:`latentforce.io.data`.
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.compile import jit, numbers, require_x64
from latentforce.models import LatentForceModel, Sensor


class Simulation(NamedTuple):
    """True trajectories at the sample times; arrays ``(T, ndof)`` / ``(T, nforce)``."""

    time: np.ndarray
    displacement: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    force: np.ndarray
    force_dofs: tuple[int, ...] = (0,)  # the DOF each latent force acts on (load cells read there)
    #: ``(T, n_internal)`` internal states (a Bouc-Wen system's hysteretic force), else ``(T, 0)``
    hysteretic_force: np.ndarray | None = None


def gp_force(key, model: LatentForceModel, params: dict, n: int, dt: float, x0=None) -> jnp.ndarray:
    """``n`` samples, spaced ``dt``, of each latent force from its stationary GP: ``(n, nforce)``;
    from the force states ``x0`` (``(nforce, kernel.dim)``) instead of a stationary draw where given."""
    kp = model.kernel_params(params)
    A, Q = model.kernel.discretise(kp, dt)
    Pinf = model.kernel.state_space(kp).Pinf
    d = model.kernel.dim
    key0, key_steps = jax.random.split(key)
    chol_p = jnp.linalg.cholesky(Pinf)
    # Q can be numerically rank deficient for long lengthscales: eigen square root.
    w, V = jnp.linalg.eigh(Q)
    sq_q = V * jnp.sqrt(jnp.clip(w, 0.0))
    if x0 is None:
        x0 = (chol_p @ jax.random.normal(key0, (d, model.nforce))).T  # (nforce, d)
    x0 = jnp.asarray(x0, dtype=float)

    def _step(x, k):
        x = x @ A.T + jax.random.normal(k, x.shape) @ sq_q.T
        return x, x[:, 0]

    _, u = jax.lax.scan(_step, x0, jax.random.split(key_steps, n - 1))
    return jnp.concatenate([x0[None, :, 0], u], axis=0)


def integrate(model: LatentForceModel, params: dict, force_fine, dt_fine: float, z0=None, v0=None, r0=None):
    """RK4 over a fine force grid ``(n, nforce)``; returns ``z, v, a, r`` at every fine point
    (``r``: the internal states, ``(n, 0)`` for a system without; they start at ``r0`` or 0, the
    virgin state)."""
    system, L = model.system, model.layout
    nd = model.ndof
    z0 = jnp.zeros(nd) if z0 is None else jnp.asarray(z0, dtype=float)
    v0 = jnp.zeros(nd) if v0 is None else jnp.asarray(v0, dtype=float)
    r0 = jnp.zeros(L.n_internal) if r0 is None else jnp.asarray(r0, dtype=float)
    force_fine = jnp.asarray(force_fine, dtype=float)

    def deriv(state, u):
        z, v, r = L.split_mech(state)
        return jnp.concatenate([v, system.acceleration(params, z, v, u, r), system.internal_rate(params, z, v, r)])

    def _step(state, inputs):
        u0, u1 = inputs
        um = 0.5 * (u0 + u1)
        k1 = deriv(state, u0)
        k2 = deriv(state + 0.5 * dt_fine * k1, um)
        k3 = deriv(state + 0.5 * dt_fine * k2, um)
        k4 = deriv(state + dt_fine * k3, u1)
        new = state + dt_fine / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        return new, new

    s0 = jnp.concatenate([z0, v0, r0])
    _, states = jax.lax.scan(_step, s0, (force_fine[:-1], force_fine[1:]))
    states = jnp.concatenate([s0[None], states], axis=0)
    z, v, r = L.split_mech(states)
    a = jax.vmap(lambda zz, vv, uu, rr: system.acceleration(params, zz, vv, uu, rr))(z, v, force_fine, r)
    return z, v, a, r


# one compiled program each per model structure and length, the numbers as arguments
_gp_force = functools.partial(jit, static_argnames=("model", "n", "dt"))(
    lambda key, params, x0, *, model, n, dt: gp_force(key, model, params, n, dt, x0)
)
_integrate = functools.partial(jit, static_argnames=("model", "dt"))(
    lambda params, u, start, *, model, dt: integrate(model, params, u, dt, *(start or (None, None, None)))
)


def simulate(
    key,
    model: LatentForceModel,
    params: dict,
    n_samples: int,
    dt: float,
    *,
    force: Callable | None = None,
    substeps: int = 8,
    z0=None,
    v0=None,
    initial=None,
) -> Simulation:
    """Simulate ``n_samples`` samples at spacing ``dt`` from rest (or ``z0, v0``).

    ``force(t) -> (T_fine, nforce)`` overrides the GP force (e.g. a sine). ``initial``: a
    ``(mean, cov)`` of the whole initial state (a config's ``[initial]``, the model's state
    layout): the start, mechanical and force states, is drawn from it (with ``fold_in(key, 1)``)
    and the GP force runs on from the drawn force states (``z0, v0`` must then be None).
    """
    require_x64("latentforce.simulate.simulate")
    n_fine = (n_samples - 1) * substeps + 1
    dt_fine = dt / substeps
    t_fine = np.arange(n_fine) * dt_fine
    L = model.layout
    xf0 = r0 = None
    if initial is not None:
        if z0 is not None or v0 is not None:
            raise ValueError("give either initial or z0, v0")
        mean, cov = (np.asarray(a, dtype=float) for a in initial)
        w, V = np.linalg.eigh(0.5 * (cov + cov.T))
        x = mean + (V * np.sqrt(np.clip(w, 0.0, None))) @ np.asarray(
            jax.random.normal(jax.random.fold_in(key, 1), mean.shape)
        )
        z0, v0, r0 = x[L.displacement], x[L.velocity], x[L.internal]
        xf0 = np.reshape(x[L.force_states], (model.nforce, -1))
    if force is None:
        # one compiled program: op by op, the kernel's discretisation alone compiled
        # some hundred tiny programs (about 5 s of a quick demo)
        u_fine = _gp_force(key, numbers(params), xf0, model=model, n=n_fine, dt=float(dt_fine))
    else:
        u_fine = jnp.reshape(jnp.asarray(force(t_fine), dtype=float), (n_fine, model.nforce))
    start = None if z0 is None and v0 is None else (z0, v0, r0)
    z, v, a, r = _integrate(numbers(params), u_fine, start, model=model, dt=float(dt_fine))
    pick = lambda x: np.asarray(x[::substeps])
    return Simulation(
        np.arange(n_samples) * dt, pick(z), pick(v), pick(a), pick(u_fine), tuple(model.system.force_dofs), pick(r)
    )


def clean_signal(sim: Simulation, sensor: Sensor) -> np.ndarray:
    """The noise-free signal a sensor would see (a strain gauge: ``displacement @ coefficients``;
    a load cell: the sum of the latent forces acting at its DOF, :math:`(B u)_{dof}`)."""
    if sensor.quantity == "strain":
        return sim.displacement @ np.asarray(sensor.coefficients, dtype=float)
    if sensor.quantity == "force":
        at = np.asarray([d == sensor.dof for d in sim.force_dofs], dtype=float)
        return sim.force @ at
    return getattr(sim, sensor.quantity)[:, sensor.dof]


def measure(key, sim: Simulation, sensors) -> np.ndarray:
    """Noisy measurements ``(T, n_sensors)``: each clean signal plus its sensor noise."""
    clean = np.stack([clean_signal(sim, s) for s in sensors], axis=1)
    noise = np.asarray(jax.random.normal(key, clean.shape)) * np.array([s.noise_std for s in sensors])
    return clean + noise


def truth_columns(sim: Simulation) -> dict[str, np.ndarray]:
    """Truth columns named as in the summary (``displacement``, ``force_0`` ...)."""
    out = {}
    for name in ("displacement", "velocity", "hysteretic_force", "force"):
        arr = getattr(sim, name)
        if arr is None or arr.shape[1] == 0:
            continue
        if arr.shape[1] == 1:
            out[name] = arr[:, 0]
        else:
            for j in range(arr.shape[1]):
                out[f"{name}_{j}"] = arr[:, j]
    return out
