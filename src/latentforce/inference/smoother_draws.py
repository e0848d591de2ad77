r"""Sampled trajectories of a run that samples nothing: draws from its Gaussian smoother.

``kalman``, and ``ekf``/``ukf`` with every parameter fixed, have one Gaussian posterior of the
states (the exact RTS smoother's; the extended or unscented smoother's). ``posterior.nc`` still
holds sampled trajectories ``(chain, draw, time)`` as for the samplers (INTERFACE.md), and the force
spectrum is estimated from them: forward filtering, backward sampling (Carter & Kohn 1994) from
that Gaussian, as one chain of independent draws (nothing to converge: the draws are exact ones
of the smoother's distribution), the virtual sensors' values on each path beside the states.

How many: :data:`DRAWS` at most, fewer on long records (each draw is a backward pass over the
record, :data:`SAMPLE_BUDGET` samples x draws in all) but 16 at least, and within the stored
trajectories' byte budget (:data:`latentforce.inference.mixture.PATH_BUDGET_BYTES`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.compile import call, jit, numbers
from latentforce.inference.kalman_choice import kalman_filter_for, sample_smoothed_trajectory_for
from latentforce.inference.mixture import PATH_BUDGET_BYTES, path_columns, split_columns

__all__ = ["DRAWS", "SAMPLE_BUDGET", "draw_count", "gaussian_paths", "kalman_paths"]

#: draws at most (the force spectrum's 5 % / 95 % quantiles are taken over them)
DRAWS = 64
#: samples x draws of the backward passes at most (but 16 draws at least)
SAMPLE_BUDGET = 2_000_000


def draw_count(T: int, width: int) -> int:
    """How many paths a record of ``T`` samples and ``width`` stored columns gets (module doc)."""
    n = int(np.clip(SAMPLE_BUDGET // max(T, 1), 16, DRAWS))
    return max(1, min(n, PATH_BUDGET_BYTES // (max(T, 1) * max(width, 1) * 8)))


def kalman_paths(
    key, model, params: dict, y, mask, dt: float, initial=None, outputs: tuple = (), kalman: str = "auto", n=None
) -> dict:
    """Paths ``{state: (1, n, T, width)}`` from the exact smoother of the linear ``model`` at
    ``params`` (outputs included, :func:`latentforce.inference.mixture.path_columns`); ``kalman``
    the filter's kind (:mod:`latentforce.inference.kalman_choice`)."""
    outputs = tuple(outputs)
    states, index, kept, n = _columns(model, outputs, np.shape(y)[0], n)
    paths = _kalman_draws(
        numbers(model.complete(params)),
        initial,
        jax.random.split(key, n),
        jnp.asarray(np.where(mask, y, 0.0)),
        jnp.asarray(mask),
        jnp.asarray(kept),
        model=model,
        dt=float(dt),
        outputs=outputs,
        kalman=kalman,
    )
    return split_columns(np.asarray(paths)[None], states, index)  # one chain


def _columns(model, outputs: tuple, T: int, n) -> tuple:
    """``(states, index, kept, n)``: what a path stores (:func:`path_columns`), its columns in the
    state vector, and how many paths (:func:`draw_count` unless ``n`` is given)."""
    states, index = path_columns(model, outputs)
    kept = np.concatenate([index[s] for s in states])
    return states, index, kept, draw_count(T, kept.size) if n is None else int(n)


@functools.partial(jit, static_argnames=("model", "dt", "outputs", "kalman"))
def _kalman_draws(params, initial, keys, y, mask, kept, *, model, dt, outputs, kalman):
    from latentforce.inference.kalman_mcmc import linear_gaussian
    from latentforce.outputs import output_matrix

    T = y.shape[0]
    A, Q, H, R, m0, P0 = linear_gaussian(model, params, dt, initial)
    filt = kalman_filter_for(kalman, T)(A, Q, H, R, m0, P0, y, mask)
    sample = sample_smoothed_trajectory_for(kalman, T)
    G = output_matrix(model, outputs, params) if outputs else None

    def one(k):  # one path at a time: only its kept columns are stored
        x = sample(k, A, Q, filt)
        if G is not None:
            x = jnp.concatenate([x, x @ G.T], axis=-1)
        return x[:, kept]

    return jax.lax.map(one, keys)


def gaussian_paths(key, model, smoother, params: dict, y, mask, outputs: tuple = (), n=None) -> dict:
    """Paths ``{state: (1, n, T, width)}`` from an ``ekf``/``ukf`` smoother's Gaussian at ``params``
    (``smoother``: :func:`latentforce.inference.gaussian.for_parameters`, made with ``outputs``)."""
    states, index, kept, n = _columns(model, tuple(outputs), np.shape(y)[0], n)
    mask = np.asarray(mask, dtype=bool)
    keys = jax.random.split(key, n)
    paths = call(_gaussian_draws, smoother, numbers(params), np.where(mask, y, 0.0), mask, keys, jnp.asarray(kept))
    return split_columns(np.asarray(paths)[None], states, index)  # one chain


def _gaussian_draws(smoother, params, y, mask, keys, kept):
    def one(k):  # one path at a time (each a filter and a backward sampling pass)
        sm = smoother(params, y, mask, k)
        return jnp.concatenate([sm.path, sm.output_path], axis=-1)[:, kept]

    return jax.lax.map(one, keys)
