r"""Posterior modes and their Laplace approximations, to start and shape the samplers.

On long records the parameter posterior narrows like :math:`1/\sqrt T` and
its parameters differ in scale by orders of magnitude, so a sampler started
at the user's ``init`` with a generic proposal spends its whole warm-up
finding the posterior. Here we find it first: L-BFGS (SciPy) on the exact
Kalman log posterior of the unconstrained parameters :math:`x`, with the
gradient by forward-mode autodiff (``jax.jacfwd``: the likelihood's
steady-state shortcut and the matrix exponential's squaring loop are
``while``/``fori`` loops, which forward mode differentiates and reverse mode
does not), then the Laplace covariance

.. math:: \Sigma = \big(-\nabla^2 \log \pi(\hat x)\big)^{-1}

from the Hessian (central differences of that gradient). Several starts are optimised
one after the other (one compiled gradient serves all), and
distinct optima are reported as separate modes: the ISMA 2018 paper's
§6 finds such a mixture posterior for an SDOF system whose force and
structure can trade places.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from latentforce.compile import jit


class Mode(NamedTuple):
    """A local maximum of the log posterior in the unconstrained space."""

    x: np.ndarray            # (p,) the optimum
    log_posterior: float     # log pi(x) at the optimum (unnormalised)
    cov: np.ndarray          # (p, p) Laplace covariance; a diagonal fallback if the Hessian is not definite
    laplace_ok: bool         # the Hessian was negative definite
    log_mass: float          # Laplace estimate of the mode's log probability mass (unnormalised)


def find_modes(logdensity: Callable, starts: np.ndarray, *, args: tuple = (), max_iter: int = 200,
               same_mode_sd: float = 3.0) -> tuple[list[Mode], dict]:
    r"""Maximise ``logdensity(x, *args)`` from each row of ``starts`` ``(n, p)``; distinct optima.

    An optimum within ``same_mode_sd`` Laplace standard deviations of a
    better one is that mode again. A point where the optimiser stopped short
    (Newton decrement over 1) or where the Hessian is not negative definite
    is not reported as a mode (it is listed in the record), unless no start
    found a mode: then the best point is returned, so the chains still start
    at the best place known. Modes are returned best first (by Laplace mass).
    The second value is a record for the run's diagnostics (evaluations,
    optimiser messages, rejected points).
    """
    starts = np.atleast_2d(np.asarray(starts, dtype=float))
    n, p = starts.shape

    @jit
    def value_and_grad(x, *a):
        return logdensity(x, *a), jax.jacfwd(logdensity)(x, *a)

    evals = 0

    def objective(x):
        nonlocal evals
        evals += 1
        val, grad = (np.asarray(v, dtype=float) for v in value_and_grad(jnp.asarray(x), *args))
        if not (np.isfinite(val) and np.all(np.isfinite(grad))):
            # Outside where the model is valid (e.g. an unstable system): a wall, not a NaN.
            return 1e300, np.zeros_like(x)
        return -float(val), -grad

    xs, fs, messages = np.empty_like(starts), np.full(n, -np.inf), []
    options = {"maxiter": max_iter, "maxcor": 20, "ftol": 1e-13, "gtol": 1e-7}
    for i in range(n):
        res = scipy.optimize.minimize(objective, starts[i], jac=True, method="L-BFGS-B", options=options)
        if not res.success and res.fun < 1e299:
            # A failed line search (L-BFGS-B's "ABNORMAL") often stops short of the optimum: once more.
            res = scipy.optimize.minimize(objective, res.x, jac=True, method="L-BFGS-B", options=options)
        xs[i], fs[i] = res.x, (-res.fun if res.fun < 1e299 else -np.inf)
        messages.append(str(res.message))
    modes: list[Mode] = []
    rejected = []
    for i in np.argsort(-fs):
        if not np.isfinite(fs[i]):
            continue
        if any(_within(xs[i], m, same_mode_sd) for m in modes):
            continue  # the same mode again: no Hessian needed
        # The Hessian by central differences of the (forward-mode) gradient: one compiled
        # program serves both, where forward-over-forward took seconds more to compile.
        cov, ok = _laplace_cov(_hessian(value_and_grad, xs[i], args))
        grad = np.asarray(value_and_grad(jnp.asarray(xs[i]), *args)[1])
        # Squared Newton decrement: about twice the log density a Newton step would still
        # gain. Above 1 the optimiser stopped short, and the point is no mode.
        decrement = float(grad @ cov @ grad)
        if not (ok and decrement < 1.0):
            rejected.append({"x": xs[i].tolist(), "log_posterior": float(fs[i]), "newton_decrement": decrement,
                             "hessian_definite": ok})
            continue
        _, logdet = np.linalg.slogdet(cov)
        log_mass = float(fs[i] + 0.5 * logdet + 0.5 * p * np.log(2 * np.pi))
        modes.append(Mode(xs[i].copy(), float(fs[i]), cov, ok, log_mass))
    if not modes:
        # No definite optimum: the best point, with what curvature it has, is still the best start.
        i = int(np.argmax(fs))
        if np.isfinite(fs[i]):
            cov, ok = _laplace_cov(_hessian(value_and_grad, xs[i], args))
            modes.append(Mode(xs[i].copy(), float(fs[i]), cov, ok, float(fs[i])))
    modes.sort(key=lambda m: -m.log_mass)
    record = {"evaluations": evals, "messages": messages, "starts": n, "rejected": rejected}
    return modes, record


def _hessian(value_and_grad: Callable, x: np.ndarray, args: tuple) -> np.ndarray:
    """Central differences of the gradient, step 1e-4 per unconstrained coordinate."""
    h = 1e-4
    cols = []
    for j in range(x.size):
        e = np.zeros_like(x)
        e[j] = h
        g_plus = np.asarray(value_and_grad(jnp.asarray(x + e), *args)[1])
        g_minus = np.asarray(value_and_grad(jnp.asarray(x - e), *args)[1])
        cols.append((g_plus - g_minus) / (2 * h))
    return np.stack(cols, axis=1)


def _laplace_cov(H: np.ndarray) -> tuple[np.ndarray, bool]:
    """Inverse of the negative Hessian; where it is not definite, unit variance in the flat directions."""
    H = 0.5 * (H + H.T)
    if np.all(np.isfinite(H)):
        w, V = np.linalg.eigh(-H)
        if w.min() > 0:
            return (V / w) @ V.T, True
        # Flat or saddle directions: keep the curved ones, give the rest a unit-scale sd.
        w = np.where(w > 1e-12 * max(w.max(), 1e-300), w, 1.0)
        return (V / w) @ V.T, False
    return np.eye(H.shape[0]), False


def _within(x: np.ndarray, mode: Mode, k: float) -> bool:
    """``x`` lies within ``k`` Laplace standard deviations of ``mode`` (in its metric)."""
    d = x - mode.x
    try:
        return float(d @ np.linalg.solve(mode.cov, d)) <= k * k
    except np.linalg.LinAlgError:
        return False


def chain_starts(key, modes: list[Mode], chains: int, *, spread: float = 2.0,
                 max_log_mass_gap: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    r"""Over-dispersed chain starts ``(chains, p)`` and each chain's mode index.

    Chains are dealt round-robin to the modes whose Laplace mass is within
    ``exp(max_log_mass_gap)`` of the best, then drawn from
    :math:`N(\hat x, \text{spread}^2 \Sigma)` around their mode: dispersed
    more than the posterior, as R-hat needs.
    """
    kept = [m for m in modes if m.log_mass >= modes[0].log_mass - max_log_mass_gap]
    which = np.arange(chains) % len(kept)
    z = np.asarray(jax.random.normal(key, (chains, modes[0].x.size)))
    starts = np.stack([kept[w].x + spread * np.linalg.cholesky(kept[w].cov) @ z[c] for c, w in enumerate(which)])
    return starts, which
