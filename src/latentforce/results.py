"""The in-memory result of an inference run (:class:`RunResult`), its error measures and
parameter summaries, and the layout names of its columns.

Every inference method returns a :class:`RunResult`. Writing it as the result
folder is :mod:`latentforce.result_files` and reading one back :mod:`latentforce.result_reader` (the folder's
layout is described there); its ``write_results``, ``read_results``,
``check_out_dir``, ``redraw``, ``write_figures`` and ``FIGURE_LOCK`` are also
reachable from here, loaded on first use (the file layer imports this module,
not the other way round).
"""

from __future__ import annotations

import logging
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Iterator

import numpy as np
import xarray as xr

__all__ = [
    "RunResult",
    "nmse",
    "by_column",
    "coverage",
    "summarise_parameters",
    "summary_columns",
    "STATE_NAMES",
    "RESULT_FILES",
]

#: The mechanical and force states, in the order the summaries list them.
STATE_NAMES: tuple[str, ...] = ("displacement", "velocity", "hysteretic_force", "force")

#: The files in a result folder that ``write_results`` owns (besides
#: ``figures/``); with ``overwrite`` only these are replaced.
RESULT_FILES: tuple[str, ...] = ("posterior.nc", "summary.csv", "summary.json", "force_psd.csv")

_ENGINE = "h5netcdf"
_PATH_DRAW = "path_draw"
_UNITS = {"displacement": "m", "velocity": "m/s", "hysteretic_force": "N", "force": "N"}


@dataclass
class RunResult:
    """What every inference method returns.

    Shapes: ``T`` time steps, ``ndof`` degrees of freedom, ``nforce`` latent
    forces, ``chains`` x ``draws`` parameter draws and ``chains`` x
    ``path_draws`` thinned trajectory draws.
    """

    method: str  # "kalman" | "kalman-mcmc" | "pgas"
    time: np.ndarray  # (T,)
    ndof: int
    nforce: int
    state_mean: dict[str, np.ndarray]  # state -> (T, ndof|nforce)
    state_sd: dict[str, np.ndarray]  # state -> (T, ndof|nforce)
    param_draws: dict[str, np.ndarray]  # name -> (chains, draws); empty for kalman
    path_draws: dict[str, np.ndarray]  # state -> (chains, path_draws, T, ndof|nforce)
    sample_stats: dict[str, np.ndarray]  # name -> (chains, draws), or (chains,) for a per-chain rate
    acceptance: list[float]  # per chain; empty for kalman
    log_likelihood: float  # exact for kalman, at the point estimate otherwise
    observed: dict[str, np.ndarray]  # column -> (T,), NaN where missing
    truth: dict[str, np.ndarray] = field(default_factory=dict)  # state -> (T, n)
    point_estimate: dict[str, float] = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)  # JSON-able extras
    seed: int = 0
    wall_time_s: float = 0.0
    fixed: dict[str, float] = field(default_factory=dict)
    #: Parameter summaries computed from the full chains, when ``param_draws``
    #: holds only the draws aligned with ``path_draws`` (see ``posterior.nc``).
    param_summary: dict | None = None
    #: The full post-burn-in parameter chains (name -> ``(chains, draws)``) where ``param_draws``
    #: holds only the draws aligned with ``path_draws``; empty when they are the same.
    param_chains: dict[str, np.ndarray] = field(default_factory=dict)
    #: The convergence record (:func:`latentforce.inference.convergence.diagnose`);
    #: None for ``kalman``, which has no sampling error.
    convergence: dict | None = None
    #: column -> {"unit" (SI, what ``observed`` carries), "original", "scale", "source"}
    #: (:func:`latentforce.io.channels.channel_units`); empty when unknown
    units: dict = field(default_factory=dict)
    #: Virtual sensors ``{name: unit}``; their means, sds and paths sit in ``state_mean``,
    #: ``state_sd`` and ``path_draws`` under their names (:mod:`latentforce.outputs`).
    outputs: dict[str, str] = field(default_factory=dict)
    #: The ``force_psd.csv`` table (:mod:`latentforce.spectrum`), None where there is none.
    force_psd: dict | None = None


# ---------------------------------------------------------------------------
# Error measures and parameter summaries
# ---------------------------------------------------------------------------


def nmse(truth: np.ndarray, estimate: np.ndarray) -> float:
    """Normalised mean squared error in percent.

    .. math:: \\mathrm{NMSE} = \\frac{100}{T\\,\\sigma_x^2} \\sum_t (x_t - \\hat x_t)^2

    with :math:`\\sigma_x^2` the (population) variance of the truth, as in
    the Vibration 2020 paper. Pairs where either value is not finite are
    left out; a constant truth gives ``nan``.
    """
    x = np.asarray(truth, dtype=float).ravel()
    xhat = np.asarray(estimate, dtype=float).ravel()
    if x.shape != xhat.shape:
        raise ValueError(f"nmse: truth has {x.size} values, estimate {xhat.size}")
    ok = np.isfinite(x) & np.isfinite(xhat)
    if not ok.any():
        return float("nan")
    x, xhat = x[ok], xhat[ok]
    variance = np.var(x)
    if variance <= 0.0:
        return float("nan")
    return float(100.0 * np.mean((x - xhat) ** 2) / variance)


def coverage(truth: np.ndarray, mean: np.ndarray, sd: np.ndarray, k: float = 3.0) -> float:
    """Fraction of values with ``|truth - mean| <= k * sd`` (calibration check).

    For a calibrated Gaussian posterior this is about 0.683, 0.954 and
    0.997 for ``k`` = 1, 2, 3. Non-finite entries are left out.
    """
    x, m, s = (np.asarray(a, dtype=float) for a in (truth, mean, sd))
    x, m, s = np.broadcast_arrays(x, m, s)
    ok = np.isfinite(x) & np.isfinite(m) & np.isfinite(s)
    if not ok.any():
        return float("nan")
    return float(np.mean(np.abs(x[ok] - m[ok]) <= k * s[ok]))


def by_column(score, truth: dict, *estimates: dict) -> dict[str, float]:
    """``score(truth, *estimates)`` (:func:`nmse`, :func:`coverage`) of every column of each state in
    ``truth`` (``(T,)`` or ``(T, width)``), keyed as ``summary.json``'s ``nmse``: ``displacement`` for one
    column, ``displacement_0``, ``displacement_1`` ... for several (an MDOF structure's DOFs, its forces)."""
    out = {}
    for name, x in truth.items():
        if any(name not in e for e in estimates):
            continue
        cols = [np.asarray(a, dtype=float).reshape(np.shape(a)[0], -1) for a in (x, *(e[name] for e in estimates))]
        width = cols[0].shape[1]
        for i in range(width):
            out[_component_label(name, i, width)] = score(*(c[:, i] for c in cols))
    return out


@contextmanager
def _quiet_arviz() -> Iterator[Any]:
    """Import ArviZ without its refactor FutureWarning and small-sample logs.

    ArviZ logs a shape warning for fewer than 2 chains or 4 draws and then
    returns NaN, which we report as ``null``; the warning adds nothing.
    """
    logger = logging.getLogger("arviz")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import arviz

            yield arviz
    finally:
        logger.setLevel(level)


def summarise_parameters(param_draws: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Posterior summary of each sampled scalar parameter.

    ``param_draws`` maps a name to draws of shape ``(chains, draws)``. Returns
    ``{name: {mean, sd, median, q05, q95, r_hat, ess_bulk}}``: moments and
    quantiles over all chains pooled, rank-normalised split R-hat
    (``arviz.rhat``) and bulk ESS (``arviz.ess(method="bulk")``). R-hat is
    NaN for a single chain and both are NaN for fewer than 4 draws.
    """
    if not param_draws:
        return {}
    arrays = {name: _as_chain_draw(name, draws) for name, draws in param_draws.items()}
    dataset = xr.Dataset({name: (("chain", "draw"), a) for name, a in arrays.items()})
    one_chain = min(a.shape[0] for a in arrays.values()) < 2
    with _quiet_arviz() as az:
        # (arviz logs a shape warning for one chain past the quieting: NaN without asking)
        r_hat = {name: np.nan for name in arrays} if one_chain else az.rhat(dataset)
        ess_bulk = az.ess(dataset, method="bulk")
    summary = {}
    for name, a in arrays.items():
        flat = a.ravel()
        summary[name] = {
            "mean": float(np.mean(flat)),
            "sd": float(np.std(flat, ddof=1)) if flat.size > 1 else float("nan"),
            "median": float(np.median(flat)),
            "q05": float(np.quantile(flat, 0.05)),
            "q95": float(np.quantile(flat, 0.95)),
            "r_hat": float(r_hat[name]),
            "ess_bulk": float(ess_bulk[name]),
        }
    return summary


def _as_chain_draw(name: str, draws: np.ndarray) -> np.ndarray:
    a = np.asarray(draws, dtype=float)
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2:
        raise ValueError(f"parameter draws {name!r} must be (chains, draws), got {a.shape}")
    return a


# ---------------------------------------------------------------------------
# Shapes and names
# ---------------------------------------------------------------------------


def _width(result: RunResult, state: str, array: np.ndarray | None = None) -> int:
    """Number of components of a state: ndof, nforce, or its array's width."""
    if state in ("displacement", "velocity"):
        return int(result.ndof)
    if state == "force":
        return int(result.nforce)
    if array is None:
        return 1
    a = np.asarray(array)
    return 1 if a.ndim < 2 else int(a.shape[-1])


def _component_dim(state: str) -> str:
    if state in ("displacement", "velocity"):
        return "dof"
    if state == "force":
        return "force_index"
    return f"{state}_index"


def _ordered_states(names) -> list[str]:
    names = list(names)
    return [s for s in STATE_NAMES if s in names] + [s for s in names if s not in STATE_NAMES]


def _as_time_width(array: np.ndarray, T: int, width: int, what: str) -> np.ndarray:
    a = np.asarray(array, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.shape != (T, width):
        raise ValueError(f"{what} must have shape ({T}, {width}), got {a.shape}")
    return a


def _component_label(state: str, i: int, width: int) -> str:
    return state if width == 1 else f"{state}_{i}"


def summary_columns(result: RunResult) -> list[str]:
    """The header of ``summary.csv`` for this result."""
    columns = ["time"]
    for state in _ordered_states(result.state_mean):
        width = _width(result, state, result.state_mean[state])
        for i in range(width):
            label = _component_label(state, i, width)
            columns += [f"{label}_mean", f"{label}_sd"]
    return columns


#: names served by :mod:`latentforce.result_files` and :mod:`latentforce.result_reader`, imported on first
#: use (no import cycle)
_FILE_API = {
    **dict.fromkeys(("write_results", "check_out_dir", "redraw", "write_figures", "FIGURE_LOCK"), "result_files"),
    "read_results": "result_reader",
}


def __getattr__(name: str):
    if name in _FILE_API:
        import importlib

        return getattr(importlib.import_module(f"latentforce.{_FILE_API[name]}"), name)
    raise AttributeError(f"module 'latentforce.results' has no attribute {name!r}")
