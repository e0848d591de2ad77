r"""The posterior force's power spectral density, with the GP prior's beside it.

Convention: every density here is *one-sided* in hertz, as
:func:`scipy.signal.welch` returns with ``scaling="density"``: for a
stationary force of variance :math:`\sigma_f^2`,

.. math:: G(f) = 2\,S(2\pi f) \quad (f \ge 0), \qquad \int_0^\infty G(f)\,df = \sigma_f^2,

with :math:`S(\omega)` the kernel's two-sided density in angular frequency
(:meth:`latentforce.kernels.Matern.spectral_density`, normalised to
:math:`\int S\,d\omega/2\pi = \sigma_f^2`). Units: force² per hertz (N²/Hz).

The posterior spectrum is the Welch estimate (Hann window, segments of
``nperseg`` samples, half overlap, the mean removed per segment) of each
posterior sample path of the force; its mean and 5 % / 95 % quantiles over
the paths are reported per frequency. The sample paths are the run's stored
trajectories: the samplers' draws (``kalman-mcmc``, ``kalman-nuts``,
``pgas``, ``ekf``/``ukf`` with inferred parameters), or, under ``kalman``
and ``ekf``/``ukf`` at fixed parameters, draws from their smoother's
Gaussian by forward filtering, backward sampling
(:mod:`latentforce.inference.smoother_draws`). The prior's density is drawn
at the posterior median of the force hyperparameters (the fixed values under
``kalman``).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from scipy.signal import welch

from latentforce.kernels import KernelParams
from latentforce.models import hyper_names

__all__ = [
    "force_psd_table",
    "force_spectrum",
    "prior_psd",
    "welch_psd",
]

#: Welch segment length at most (scipy's default); shorter records use the whole record
NPERSEG = 256


def prior_psd(kernel, variance: float, lengthscale: float, frequency: np.ndarray) -> np.ndarray:
    r"""One-sided PSD :math:`G(f) = 2 S(2\pi f)` of the GP prior (module doc), force²/Hz."""
    kp = KernelParams(jnp.asarray(variance, dtype=float), jnp.asarray(lengthscale, dtype=float))
    return 2.0 * np.asarray(kernel.spectral_density(2.0 * np.pi * np.asarray(frequency, dtype=float), kp))


def welch_psd(paths: np.ndarray, dt: float, nperseg: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(frequency, psd)``: the one-sided Welch density of each path along the last axis."""
    paths = np.asarray(paths, dtype=float)
    T = paths.shape[-1]
    nperseg = min(T, NPERSEG) if nperseg is None else min(T, int(nperseg))
    return welch(paths, fs=1.0 / dt, nperseg=nperseg, axis=-1)


def force_psd_table(
    force_paths: np.ndarray,
    dt: float,
    kernel,
    variance: float,
    lengthscale: float,
    truth: np.ndarray | None = None,
    nperseg: int | None = None,
) -> dict[str, np.ndarray]:
    """The ``force_psd.csv`` table from force sample paths ``(n_paths, T, nforce)``.

    Columns ``frequency``, ``psd_mean``, ``psd_q05``, ``psd_q95``, ``prior_psd``
    (and ``truth_psd`` when the true force is known); with several latent
    forces the posterior and truth columns carry a suffix ``_j``.
    """
    paths = np.moveaxis(np.asarray(force_paths, dtype=float), 1, -1)  # (n_paths, nforce, T)
    freq, psd = welch_psd(paths, dt, nperseg)
    nforce = paths.shape[1]
    table = {"frequency": freq}
    for j in range(nforce):
        sfx = "" if nforce == 1 else f"_{j}"
        table[f"psd_mean{sfx}"] = psd[:, j].mean(axis=0)
        table[f"psd_q05{sfx}"] = np.quantile(psd[:, j], 0.05, axis=0)
        table[f"psd_q95{sfx}"] = np.quantile(psd[:, j], 0.95, axis=0)
    # a product kernel has no closed-form density here (a Matérn sum has: the terms summed)
    table["prior_psd"] = (
        prior_psd(kernel, variance, lengthscale, freq)
        if hasattr(kernel, "spectral_density")
        else np.full(freq.shape, np.nan)
    )
    if truth is not None:
        truth = np.asarray(truth, dtype=float).reshape(len(truth), -1)
        _, psd_true = welch_psd(truth.T, dt, nperseg)
        for j in range(nforce):
            table["truth_psd" if nforce == 1 else f"truth_psd_{j}"] = psd_true[j]
    return table


def hyperparameters(result, fixed: dict, model) -> tuple:
    """The force variance and lengthscale at which the prior is drawn: the posterior median of a
    sampled one, else its fixed value (for a kernel sum, arrays with one entry per term)."""
    var_names, ls_names = hyper_names(model.kernel, split=True)
    summary = result.param_summary or {}

    def value(name):
        draws = result.param_draws.get(name)
        if name in summary and summary[name].get("median") is not None:
            return float(summary[name]["median"])
        if draws is not None and np.size(draws):
            return float(np.median(draws))
        return float(fixed[name])

    var, ls = [value(n) for n in var_names], [value(n) for n in ls_names]
    return (var[0], ls[0]) if len(var) == 1 else (np.array(var), np.array(ls))


def force_spectrum(problem, result, params: dict, dt: float) -> dict | None:
    """The ``force_psd.csv`` table of a run from its stored force paths (module doc); ``None`` where
    none exist."""
    model = problem.model
    f = result.path_draws.get("force")
    if f is None or np.size(f) == 0:
        return None
    f = np.asarray(f, dtype=float)
    paths = f.reshape(-1, f.shape[2], f.shape[3])
    variance, lengthscale = hyperparameters(result, params, model)
    return force_psd_table(paths, dt, model.kernel, variance, lengthscale, truth=result.truth.get("force"))
