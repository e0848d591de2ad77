r"""The states' posterior mixed over parameter draws, in memory independent of the draws.

Given parameter draws :math:`\theta_j` (``kalman-mcmc``, ``kalman-nuts``),
the states' posterior is the mixture of the exact smoothers
:math:`N(m_t(\theta_j), P_t(\theta_j))`. By the law of total variance

.. math:: E[x_t] = \overline{m_t(\theta_j)}, \qquad
          \operatorname{Var}[x_t] = \overline{P_t(\theta_j)} + \operatorname{Var}_j[m_t(\theta_j)].

The sums are accumulated batch by batch (Chan et al.'s pairwise update of
mean and sum of squared deviations, stable in float64), so memory is a
batch of smoothers plus three ``(T, n)`` accumulators, whatever the number
of draws (and on a long complete record each smoother keeps its
covariances in steady state, :mod:`latentforce.inference.steady`); backward-sampled
trajectories (Carter & Kohn) are kept for a
bounded number of draws only, within :data:`PATH_BUDGET_BYTES`.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.compile import bound, jit, numbers
from latentforce.inference import steady
from latentforce.inference.kalman_choice import (
    kalman_filter_for,
    rts_smoother_for,
    sample_smoothed_trajectory_for,
    use_parallel,
)
from latentforce.models import LatentForceModel

#: bytes of stored trajectories (``posterior.nc``'s paths) at most
PATH_BUDGET_BYTES = 256 * 2**20
#: bytes of one batch's filter and smoother arrays at most
BATCH_BUDGET_BYTES = 32 * 2**20


class Mixture(NamedTuple):
    """What :func:`mixture_posterior` returns (NumPy arrays)."""

    moments: dict  # state -> (mean (T, width), sd (T, width))
    paths: dict  # state -> (chains, paths_per_chain, T, width)
    path_index: np.ndarray  # (paths_per_chain,) draw index of each chain's stored paths
    n_mix: int  # parameter draws mixed
    point: tuple | None  # (moments, log-likelihood) of the smoother at ``point``


def path_columns(model: LatentForceModel, outputs: tuple = ()) -> tuple[tuple, dict]:
    """``(names, {name: columns})``: the states a stored path holds and their columns in the state
    vector, the ``outputs`` (virtual sensors) after it at ``n_state + i``."""
    index = {q: model.layout.index(q) for q in model.layout.states}
    index.update({o.name: np.array([model.n_state + i]) for i, o in enumerate(outputs)})
    return model.layout.states + tuple(o.name for o in outputs), index


def split_columns(paths: np.ndarray, states: tuple, index: dict) -> dict:
    """Stored paths ``(..., kept)``, their columns those of :func:`path_columns` in ``states`` order,
    as ``{state: (..., width)}``."""
    offsets = np.cumsum([0] + [len(index[s]) for s in states])
    return {s: paths[..., offsets[i] : offsets[i + 1]] for i, s in enumerate(states)}


def mixture_size(T: int, chains: int, n_draws: int, thin_draws: int, width: int) -> tuple[int, int]:
    """``(draws mixed per chain, paths stored per chain)`` for a record of ``T`` samples.

    Up to 50 draws per chain mixed, fewer on long records (each costs a
    smoother over ``T``; at least 16 per chain: the between-draw variance is
    a small part of the total where the posterior is narrow); paths at most
    ``thin_draws`` per chain and :data:`PATH_BUDGET_BYTES` in all.
    """
    per_chain = int(np.clip(2.5e6 // max(T, 1) // max(chains, 1), 16, 50))
    per_chain = min(per_chain, n_draws)
    paths = int(min(thin_draws, max(1, PATH_BUDGET_BYTES // (chains * T * width * 8)), per_chain))
    return per_chain, max(paths, 1)


def _one(
    model: LatentForceModel,
    fixed: dict,
    names: tuple,
    dt: float,
    initial,
    outputs: tuple,
    smoother,
    kalman: str,
    with_path: bool,
    steady_K: int | None,
    key,
    theta,
    y,
    mask,
):
    r"""One draw's smoothed means, variances, (path) and log-likelihood; a flag that it is exact.

    With ``outputs`` (:class:`latentforce.outputs.OutputSpec`), the state columns are followed by
    the outputs :math:`G_\theta x`: means :math:`G m_t`, variances
    :math:`\operatorname{diag}(G P_t G^T)` from the full covariances, and the path's outputs.
    ``smoother(params, y, mask, key)`` replaces the exact Kalman smoother (``ekf``/``ukf``; it returns
    the outputs' moments itself, :func:`latentforce.inference.gaussian.for_parameters`).
    ``steady_K``: the steady-state smoother with that transient, else (None) the full one.
    """
    from latentforce.inference.kalman_mcmc import linear_gaussian
    from latentforce.outputs import output_matrix

    params = _params(fixed, names, theta)
    if smoother is not None:  # ekf / ukf (inference/gaussian.py), the outputs by its own transform
        sm = smoother(params, y, mask, key if with_path else None)
        join = lambda a, b: jnp.concatenate([a, b], axis=-1)  # noqa: E731
        var = join(jnp.diagonal(sm.covs, axis1=-2, axis2=-1), sm.output_vars)
        path = join(sm.path, sm.output_path) if with_path else jnp.zeros(())
        return join(sm.means, sm.output_means), var, path, sm.log_likelihood, jnp.ones((), bool)
    G = output_matrix(model, outputs, params) if outputs else None
    extend = (lambda x: x) if G is None else (lambda x: jnp.concatenate([x, x @ G.T], axis=-1))
    A, Q, H, R, m0, P0 = linear_gaussian(model, params, dt, initial)
    if steady_K is not None:
        sm = steady.steady_smoother(A, Q, H, R, m0, P0, y, key if with_path else None, K=steady_K, rows=G)
        path = extend(sm.path) if with_path else jnp.zeros(())
        return extend(sm.means), sm.variances, path, sm.log_likelihood, sm.converged
    T = y.shape[0]
    filt = kalman_filter_for(kalman, T)(A, Q, H, R, m0, P0, y, mask)
    sm = rts_smoother_for(kalman, T)(A, filt)
    var = jnp.diagonal(sm.covs, axis1=-2, axis2=-1)
    if G is not None:
        var = jnp.concatenate([var, jnp.einsum("ki,tij,kj->tk", G, sm.covs, G)], axis=-1)
    path = extend(sample_smoothed_trajectory_for(kalman, T)(key, A, Q, filt)) if with_path else jnp.zeros(())
    return extend(sm.means), var, path, filt.log_likelihood, jnp.ones((), bool)


def mixture_posterior(
    key,
    model: LatentForceModel,
    fixed: dict,
    draws: dict,
    y,
    mask,
    dt: float,
    *,
    thin_draws: int = 200,
    initial=None,
    point: dict | None = None,
    outputs: tuple = (),
    smoother=None,
    kalman: str = "auto",
) -> Mixture:
    """The mixed state posterior over thinned ``draws`` ``{name: (chains, n)}``; see the module doc.

    ``outputs`` (virtual sensors, :mod:`latentforce.outputs`) are mixed likewise and returned
    under their names beside the states, in ``moments`` and ``paths``.
    ``smoother(params, y, mask, key)`` replaces the exact Kalman smoother (``ekf``/``ukf``:
    :func:`latentforce.inference.gaussian.for_parameters`, made with the same ``outputs``).

    ``kalman`` (:mod:`latentforce.inference.kalman_choice`): where it picks the
    parallel scan, every draw gets the full parallel filter and smoother (the
    steady-state smoother is a sequential scan) and batches are sized for the
    scan's larger working memory.
    """
    names = tuple(draws)
    outputs = tuple(outputs)
    chains, n_iter = next(iter(draws.values())).shape
    T, n = np.shape(y)[0], model.n_state
    states, index = path_columns(model, outputs)
    width = sum(len(ix) for ix in index.values())
    per_chain, n_paths = mixture_size(T, chains, n_iter, thin_draws, width)
    idx = np.linspace(0, n_iter - 1, per_chain).round().astype(int)
    path_slots = np.linspace(0, per_chain - 1, n_paths).round().astype(int)
    thetas = np.stack([draws[nm][:, idx] for nm in names], axis=-1)  # (chains, per_chain, p)
    is_path = np.zeros((chains, per_chain), bool)
    is_path[:, path_slots] = True

    # A complete long record: covariances in steady state (O(T n) memory per draw), else the full smoother.
    parallel = use_parallel(kalman, T)
    # numbers (arguments of the compiled programs) and structure (their static arguments)
    fixed = numbers(model.complete(fixed))
    smoother = None if smoother is None else bound(smoother)
    static = dict(model=model, names=names, dt=float(dt))
    steady_K = None
    # (Only where the longest transient fits twice: on shorter records the probe's compile, about
    # 2 s, outweighs what the steady state saves; measured at T = 2 000.)
    if smoother is None and steady.applies(T, bool(np.all(mask))) and not parallel:
        # The transient from the settling of the slowest of a few draws (the filter's covariance
        # does not depend on the data): a lightly damped structure needs more than a stiff one.
        probe = thetas.reshape(-1, len(names))[np.linspace(0, chains * per_chain - 1, 8).round().astype(int)]
        settle = _settle(fixed, initial, jnp.asarray(probe), max_steps=steady.TRANSIENT, **static)
        steady_K = steady.transient_for(int(np.max(np.asarray(settle))), T)
    # the associative scans hold about three times the sequential smoother's arrays
    per_draw = T * (4 * n + 2) * 8 if steady_K else T * ((12 if parallel else 4) * n * n + 4 * n) * 8
    batch = int(max(1, min(16, BATCH_BUDGET_BYTES // per_draw)))
    y = jnp.asarray(np.where(mask, y, 0.0))
    mask = jnp.asarray(mask)
    # For draws that settle later than the probes: a longer transient, then the full smoother.
    fallbacks = []
    if steady_K:
        fallbacks = [K for K in (2 * steady_K, steady.TRANSIENT) if K > steady_K and steady.applies(T, True, K)]
        fallbacks = sorted(set(fallbacks)) + [None]

    def program(with_path, K):
        return functools.partial(
            _batch, fixed, initial, smoother, outputs=outputs, kalman=kalman, with_path=with_path, steady_K=K, **static
        )

    def smoothers(with_path, ks, th):
        """The batch's smoothers; a draw whose covariances did not settle is redone with a longer
        transient, and in full if need be (only those draws: the batch's rest repeats the first)."""
        means, var, path, ll, exact = (np.array(a) for a in program(with_path, steady_K)(ks, th, y, mask))
        for K in fallbacks:
            if exact.all():
                break
            redo = np.flatnonzero(~exact)
            pick = np.concatenate([redo, np.full(len(exact) - len(redo), redo[0])])
            again = [np.asarray(a) for a in program(with_path, K)(ks[pick], th[pick], y, mask)]
            for target, source in zip((means, var, path, ll, exact), again):
                target[redo] = source[: len(redo)]
        return means, var, path, ll

    acc = _Accumulator(T, n + len(outputs))
    kept = np.concatenate([index[s] for s in states])  # the state components a path stores
    paths = np.zeros((chains, n_paths, T, kept.size))
    keys = np.asarray(jax.random.key_data(jax.random.split(key, chains * per_chain)))
    keys = keys.reshape(chains, per_chain, *keys.shape[1:])
    for with_path, select in ((True, is_path), (False, ~is_path)):
        where = np.argwhere(select)  # (count, 2): (chain, slot)
        for start in range(0, len(where), batch):
            part = where[start : start + batch]
            pad = np.concatenate([part, np.repeat(part[-1:], batch - len(part), axis=0)])
            th = jnp.asarray(thetas[pad[:, 0], pad[:, 1]])
            ks = jax.random.wrap_key_data(jnp.asarray(keys[pad[:, 0], pad[:, 1]]))
            means, var, path, _ = smoothers(with_path, ks, th)
            k = len(part)
            acc.add(means[:k], var[:k])
            if with_path:
                slot = np.searchsorted(path_slots, part[:, 1])
                paths[part[:, 0], slot] = path[:k][..., kept]
    mean, var = acc.result()
    moments = {s: (mean[:, ix], np.sqrt(np.clip(var[:, ix], 0.0, None))) for s, ix in index.items()}
    sampled = split_columns(paths, states, index)
    point_result = None
    if point is not None:
        th = jnp.repeat(jnp.asarray([[float(point[nm]) for nm in names]]), batch, axis=0)
        # through the program the paths used (compiled already); the path is not kept
        m_p, v_p, _, ll = smoothers(True, jax.random.split(key, batch), th)
        m_p, v_p = m_p[0], v_p[0]
        point_result = (
            {s: (m_p[:, ix], np.sqrt(np.clip(v_p[:, ix], 0.0, None))) for s, ix in index.items()},
            float(ll[0]),
        )
    return Mixture(moments, sampled, idx[path_slots], chains * per_chain, point_result)


def _params(fixed: dict, names: tuple, theta) -> dict:
    """The known values with one draw's ``theta`` (ordered as ``names``) in place."""
    params = dict(fixed)
    for i, n in enumerate(names):
        params[n] = theta[i]
    return params


@functools.partial(jit, static_argnames=("model", "names", "dt", "max_steps"))
def _settle(fixed, initial, thetas, *, model, names, dt, max_steps):
    """The filter covariance's settling steps (:func:`steady.settling_steps`) at each row of ``thetas``."""
    from latentforce.inference.kalman_mcmc import linear_gaussian

    def one(theta):
        A, Q, H, R, _, P0 = linear_gaussian(model, _params(fixed, names, theta), dt, initial)
        return steady.settling_steps(A, Q, H, R, P0, max_steps)

    return jax.vmap(one)(thetas)


@functools.partial(jit, static_argnames=("model", "names", "dt", "outputs", "kalman", "with_path", "steady_K"))
def _batch(fixed, initial, smoother, keys, thetas, y, mask, *, model, names, dt, outputs, kalman, with_path, steady_K):
    """:func:`_one` over a batch of draws: one program per structure, shape and smoother kind."""
    return jax.vmap(
        lambda k, th: _one(
            model, fixed, names, dt, initial, outputs, smoother, kalman, with_path, steady_K, k, th, y, mask
        )
    )(keys, thetas)


class _Accumulator:
    """Running mean of the means, their sum of squared deviations, and mean of the variances."""

    def __init__(self, T: int, n: int):
        self.count = 0
        self.mean = np.zeros((T, n))
        self.m2 = np.zeros((T, n))
        self.var = np.zeros((T, n))

    def add(self, means: np.ndarray, variances: np.ndarray) -> None:
        k = means.shape[0]
        b_mean = means.mean(0)
        b_m2 = ((means - b_mean) ** 2).sum(0)
        total = self.count + k
        delta = b_mean - self.mean
        self.mean += delta * (k / total)
        self.m2 += b_m2 + delta**2 * (self.count * k / total)
        self.var += (variances.sum(0) - k * self.var) / total
        self.count = total

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """Mixture mean and variance (law of total variance, population variance of the means)."""
        return self.mean, self.var + self.m2 / self.count
