r"""Where ``pgas`` starts when it samples system parameters: the mode of the extended Kalman filter's posterior.

A system parameter's posterior is often far narrower than its prior (k3 of
the Vibration 2020 Duffing case with a displacement channel: a few per cent
against a prior spanning a factor of 2.7 at 1 sd), and the joint move that
samples it (:func:`latentforce.inference.smoother_move.joint_move`) is a
random walk. Started at ``init`` dispersed by :math:`e^{0.5\varepsilon}` (the
hyperparameters' start), chains sat where they started: on ``demo
duffing-params --quick`` c and k3 kept R-hat 1.6 and 2.3 with a bulk ESS of 3,
each chain's walk having shrunk its steps in the directions it could not
move. As the linear samplers do (:mod:`latentforce.inference.laplace`), we
find the posterior first: L-BFGS on the log prior plus the extended Kalman
filter's log-likelihood (:mod:`latentforce.inference.gaussian`) over the
joint coordinates :math:`x = \log\theta` (hyperparameters, then system
parameters), then the Laplace covariance there. The chains start from
:math:`N(\hat x, 2^2\Sigma)` (over-dispersed, as R-hat needs) and the joint
walk's proposal starts with the shape :math:`2.38^2\Sigma/d`. The filter's
likelihood is an approximation: the sampler's moves target the exact model,
so a biased mode only costs burn-in.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.inference import gaussian, laplace
from latentforce.inference.hyper_moves import Hyper


def log_posterior(x, loglik, hyper: Hyper, fixed: dict, y, mask, R):
    """Log prior (log-space Jacobians included) plus the extended Kalman filter's log-likelihood at
    the joint coordinates ``x``; ``fixed``: every other parameter."""
    p = len(hyper.names)
    theta = jnp.exp(x[:p])
    params = dict(fixed)
    params.update({n: theta[i] for i, n in enumerate(hyper.names)})
    params.update(hyper.system_values(x[p:]))
    pm, tr, _ = gaussian._build(loglik.static, loglik.numbers, params)
    return hyper.joint_log_prior(x) + gaussian.gaussian_log_likelihood("ekf", pm, tr, y, mask, R)


def mode_start(model, hyper: Hyper, params: dict, y, mask, R, dt: float, discretisation: str, initial):
    """``(x_mode, cov, record)``: the mode of :func:`log_posterior` from the initial values and its
    Laplace covariance (:func:`fallback_cov` where the search found no definite mode: ``x_mode`` is
    then the best point it reached), and a record for the run's diagnostics."""
    loglik, _ = gaussian.for_parameters("ekf", model, dt, discretisation, initial)
    x0 = np.asarray(hyper.joint_coordinates(np.concatenate([hyper.init, hyper.sys_init])))
    fixed = {n: jnp.asarray(v, dtype=float) for n, v in params.items() if n not in hyper.joint_names}
    args = (loglik, hyper, fixed, jnp.asarray(y), jnp.asarray(mask), jnp.asarray(R))
    modes, record = laplace.find_modes(log_posterior, x0[None], args=args)
    best = modes[0]
    cov = np.asarray(best.cov) if best.laplace_ok else fallback_cov(best.cov)
    names = hyper.joint_names
    out = {
        "mode": {n: float(v) for n, v in zip(names, np.asarray(hyper.joint_values(jnp.asarray(best.x))))},
        "laplace_sd_log": {n: float(np.sqrt(cov[i, i])) for i, n in enumerate(names)},
        "laplace_ok": bool(best.laplace_ok),
        "evaluations": record.get("evaluations"),
    }
    return np.asarray(best.x), cov, out


#: without system parameters, the log-space sd of the hyperparameters' random-walk step and of the
#: chains' dispersed starts (``pgas.run_pgas``)
WALK_SD, START_SPREAD = 0.05, 0.5
#: log-space sds of the start's shape where the filter gave no definite mode (:func:`fallback_cov`):
#: the same bounds
FALLBACK_SD = (WALK_SD, START_SPREAD)


def fallback_cov(cov) -> np.ndarray:
    """The start's shape where the search found no definite mode: the diagonal of the Laplace
    covariance at the point it reached, its sds clipped to :data:`FALLBACK_SD` (a walk step of 0.05
    and a start spread of 0.5 in log space without system parameters). Measured on a 3-storey frame
    with a stiff cubic storey (k3 2.5e7 from init 1e7, 50 Hz): the filter's log posterior at init was
    -1e5 with gradients of 1e11-1e13 and L-BFGS did not move; the Hessian there gave variances of
    1e-15 beside 1, so the chains' walk never moved k3 (frozen at 1.3e6-8.8e6 on four chains for 900
    sweeps, the force's variance inflating to explain the data) and the unit directions spread the
    starts by a factor 40."""
    lo, hi = FALLBACK_SD
    return np.diag(np.clip(np.diag(np.asarray(cov, dtype=float)), lo * lo, hi * hi))


def dispersed(key, x_mode, cov, chains: int, spread: float = 2.0):
    """Chain starts from :math:`N(\\hat x, \\text{spread}^2 \\Sigma)`."""
    z = np.asarray(jax.random.normal(key, (chains, x_mode.size)))
    return x_mode + spread * z @ np.linalg.cholesky(cov).T
