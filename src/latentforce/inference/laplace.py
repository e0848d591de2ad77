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

from latentforce.compile import Bound, bound, jit

#: an optimum whose log posterior is this far below the best mode's is not examined (no Hessian):
#: it could carry mass only with a Laplace volume ~exp(1000) times the best's
FAR_BELOW = 1000.0


class Mode(NamedTuple):
    """A local maximum of the log posterior in the unconstrained space."""

    x: np.ndarray  # (p,) the optimum
    log_posterior: float  # log pi(x) at the optimum (unnormalised)
    cov: np.ndarray  # (p, p) Laplace covariance; a diagonal fallback if the Hessian is not definite
    laplace_ok: bool  # the Hessian was negative definite
    log_mass: float  # Laplace estimate of the mode's log probability mass (unnormalised)


@jit
def _value_and_grad(logdensity: Bound, x, *args):
    """The log density and its forward-mode gradient: one program per structure and shape."""
    return logdensity(x, *args), jax.jacfwd(logdensity)(x, *args)


def find_modes(
    logdensity: Callable, starts: np.ndarray, *, args: tuple = (), max_iter: int = 200, same_mode_sd: float = 3.0
) -> tuple[list[Mode], dict]:
    r"""Maximise ``logdensity(x, *args)`` from each row of ``starts`` ``(n, p)``; distinct optima.

    An optimum within ``same_mode_sd`` Laplace standard deviations of a
    better one is that mode again. A point where the optimiser stopped short
    (Newton decrement over 1) or where the Hessian is not negative definite
    is not reported as a mode (it is listed in the record), unless no start
    found a mode: then the best point is returned, so the chains still start
    at the best place known. Modes are returned best first (by Laplace mass).
    Starts run in order; one that climbs into the Laplace region of a mode
    already found stops there (it is that mode again), and an optimum more
    than :data:`FAR_BELOW` below the best mode is not examined.
    The second value is a record for the run's diagnostics (evaluations,
    optimiser messages, rejected points).
    """
    starts = np.atleast_2d(np.asarray(starts, dtype=float))
    n, p = starts.shape

    fn = bound(logdensity)

    def value_and_grad(x, *a):
        return _value_and_grad(fn, x, *a)

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
    laplaces: dict[int, tuple[np.ndarray, bool]] = {}  # start -> (cov, definite), computed once
    known: list[Mode] = []  # modes so far, for the early stop below

    def laplace_at(i):
        if i not in laplaces:
            # The Hessian by central differences of the (forward-mode) gradient: one compiled
            # program serves both, where forward-over-forward took seconds more to compile.
            scale = coordinate_scale(xs[i])
            laplaces[i] = _laplace_cov(_hessian(value_and_grad, xs[i], args, scale), scale)
        return laplaces[i]

    def stop_in_known_basin(x):
        # A start that has climbed to within a known mode's Laplace region is that mode again:
        # stop it there, its Hessian spared.
        if any(_within(x, m, same_mode_sd) for m in known):
            raise StopIteration

    for i in range(n):
        # After the first mode, in coordinates whitened by its Laplace covariance, x = x_hat + L u:
        # on a long record the posterior is narrow and its parameters differ in scale by orders of
        # magnitude, and L-BFGS from a dispersed start crawls along the valley (frame, T = 2e4:
        # 145 evaluations to reach the first mode's region). An affine change of variables moves
        # no optimum.
        # Before it, scaled by the start's own magnitudes (coordinate_scale): a softplus coordinate is the
        # value itself for a large parameter (a cubic stiffness of 5e8), whose gradient per unit then
        # fell below the optimiser's tolerance at once and every start stayed where it began.
        shift, L = (
            (known[0].x, np.linalg.cholesky(known[0].cov))
            if known
            else (starts[i], np.diag(coordinate_scale(starts[i])))
        )

        def fun(u, shift=shift, L=L):
            f, g = objective(shift + L @ u)
            return f, L.T @ g

        def callback(u, shift=shift, L=L):  # SciPy passes the iterate
            stop_in_known_basin(shift + L @ u)

        u0 = np.linalg.solve(L, starts[i] - shift)
        res = scipy.optimize.minimize(fun, u0, jac=True, method="L-BFGS-B", options=options, callback=callback)
        stopped = res.status == 99  # the callback's StopIteration
        if not (res.success or stopped) and res.fun < 1e299:
            # A failed line search (L-BFGS-B's "ABNORMAL") often stops short of the optimum: once more.
            res = scipy.optimize.minimize(fun, res.x, jac=True, method="L-BFGS-B", options=options, callback=callback)
            stopped = res.status == 99
        xs[i], fs[i] = shift + L @ res.x, (-res.fun if res.fun < 1e299 else -np.inf)
        messages.append("inside a known mode's Laplace region: stopped there" if stopped else str(res.message))
        if not stopped and np.isfinite(fs[i]) and not any(_within(xs[i], m, same_mode_sd) for m in known):
            mode, _ = _as_mode(xs[i], fs[i], *laplace_at(i), value_and_grad, args)
            if mode is not None:
                known.append(mode)
    modes: list[Mode] = []
    rejected = []
    for i in np.argsort(-fs):
        if not np.isfinite(fs[i]):
            continue
        if any(_within(xs[i], m, same_mode_sd) for m in modes):
            continue  # the same mode again: no Hessian needed
        if modes and fs[i] < modes[0].log_posterior - FAR_BELOW:
            rejected.append({"x": xs[i].tolist(), "log_posterior": float(fs[i]), "far_below_the_best": True})
            continue
        cov, ok = laplace_at(i)
        mode, decrement = _as_mode(xs[i], fs[i], cov, ok, value_and_grad, args)
        if mode is None:
            rejected.append(
                {
                    "x": xs[i].tolist(),
                    "log_posterior": float(fs[i]),
                    "newton_decrement": decrement,
                    "hessian_definite": ok,
                }
            )
            continue
        modes.append(mode)
    if not modes:
        # No definite optimum: the best point, with what curvature it has, is still the best start.
        i = int(np.argmax(fs))
        if np.isfinite(fs[i]):
            cov, ok = laplace_at(i)
            modes.append(Mode(xs[i].copy(), float(fs[i]), cov, ok, float(fs[i])))
    modes.sort(key=lambda m: -m.log_mass)
    record = {"evaluations": evals, "messages": messages, "starts": n, "rejected": rejected}
    return modes, record


def _as_mode(
    x: np.ndarray, f: float, cov: np.ndarray, ok: bool, value_and_grad: Callable, args: tuple
) -> tuple[Mode | None, float]:
    """The optimum ``x`` as a :class:`Mode`, or None where it is none: the Hessian is not negative
    definite, or the squared Newton decrement (about twice the log density a Newton step would
    still gain) is over 1, i.e. the optimiser stopped short. Second value: that decrement."""
    grad = np.asarray(value_and_grad(jnp.asarray(x), *args)[1])
    decrement = float(grad @ cov @ grad)
    if not (ok and decrement < 1.0):
        return None, decrement
    _, logdet = np.linalg.slogdet(cov)
    log_mass = float(f + 0.5 * logdet + 0.5 * x.size * np.log(2 * np.pi))
    return Mode(x.copy(), float(f), cov, ok, log_mass), decrement


def coordinate_scale(x: np.ndarray) -> np.ndarray:
    """A typical scale of each unconstrained coordinate at ``x``: 1, or a tenth of its magnitude where that is
    larger (a softplus coordinate is the parameter itself when it is large: k3 = 5e8 is x = 5e8, and a
    step of 1e-4 there is lost in the round-off of x, 6e-8)."""
    return np.maximum(1.0, 0.1 * np.abs(np.asarray(x, dtype=float)))


def _hessian(value_and_grad: Callable, x: np.ndarray, args: tuple, scale=None) -> np.ndarray:
    """Central differences of the gradient, step 1e-4 of each coordinate's ``scale`` (default 1)."""
    scale = np.ones(x.size) if scale is None else np.asarray(scale, dtype=float)
    cols = []
    for j in range(x.size):
        e = np.zeros_like(x)
        e[j] = h = 1e-4 * scale[j]
        g_plus = np.asarray(value_and_grad(jnp.asarray(x + e), *args)[1])
        g_minus = np.asarray(value_and_grad(jnp.asarray(x - e), *args)[1])
        cols.append((g_plus - g_minus) / (2 * h))
    return np.stack(cols, axis=1)


def _laplace_cov(H: np.ndarray, scale=None) -> tuple[np.ndarray, bool]:
    """Inverse of the negative Hessian; where it is not definite, a variance of ``scale`` squared (default 1)
    in the flat directions (found in the coordinates divided by ``scale``)."""
    scale = np.ones(H.shape[0]) if scale is None else np.asarray(scale, dtype=float)
    cov, ok = _laplace_cov_unit(H * scale[:, None] * scale[None, :])
    return cov * scale[:, None] * scale[None, :], ok


def _laplace_cov_unit(H: np.ndarray) -> tuple[np.ndarray, bool]:
    H = 0.5 * (H + H.T)
    if not np.all(np.isfinite(H)):
        return np.eye(H.shape[0]), False
    w, V = np.linalg.eigh(-H)
    ok = bool(w.min() > 0)
    if not ok:
        # Flat or saddle directions: keep the curved ones, give the rest a unit-scale sd.
        w = np.where(w > 1e-12 * max(w.max(), 1e-300), w, 1.0)
    # Every caller takes a Cholesky factor or solves with this matrix. A rough
    # likelihood (an EKF on a stiff cubic frame gave curvatures of 1e15 beside
    # flat unit directions) makes (V / w) V^T lose definiteness in rounding
    # (an eigenvalue of -2e-16), so variances are floored at 1e-12 of the
    # largest: a condition number float64 factors without loss.
    var = 1.0 / w
    var = np.maximum(var, 1e-12 * var.max())
    cov = (V * var) @ V.T
    return 0.5 * (cov + cov.T), ok


def _within(x: np.ndarray, mode: Mode, k: float) -> bool:
    """``x`` lies within ``k`` Laplace standard deviations of ``mode`` (in its metric)."""
    d = x - mode.x
    try:
        return float(d @ np.linalg.solve(mode.cov, d)) <= k * k
    except np.linalg.LinAlgError:
        return False


def chain_starts(
    key, modes: list[Mode], chains: int, *, spread: float = 2.0, max_log_mass_gap: float = 10.0
) -> tuple[np.ndarray, np.ndarray]:
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
