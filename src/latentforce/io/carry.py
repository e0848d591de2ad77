r"""A parameter's prior carried over from an earlier run's posterior.

The field workflow: a calibration run (a load cell on, or a known load)
identifies the structure; a monitoring run, with the load unknown, takes the
calibration's posterior of ``k``, ``c``, ... as its prior, so the force
estimate carries the calibration's uncertainty instead of a point value::

    [system]
    k = { prior = "posterior", from = "calib/" }            # the parameter of the same name
    c = { prior = "posterior", from = "calib/", param = "c" }

The earlier result folder's ``posterior.nc`` holds the draws of each sampled
parameter (its ``parameter_chains`` group, every post-burn-in draw, where the run
stored fewer in ``posterior``: a fit to the 100 stored draws of a 2 x 800 run came
out 11 % narrower than the chains' sd, 29.6 against 33.3); they are mapped to the samplers' space :math:`x =
\operatorname{softplus}^{-1}(\theta)`, where posteriors of positive
parameters are close to Gaussian, and fitted there by their mean and
standard deviation (:class:`latentforce.priors.SoftplusNormal`). A parameter
that may take either sign (``k3``, ``beta``, ``gamma``) is fitted on its value
(:class:`latentforce.priors.SignedNormal`).

Each parameter is carried as its marginal: correlations between carried
parameters are not kept (the joint prior is the product of the marginals),
which can only widen the monitoring run's posterior, never narrow it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np

from latentforce.errors import LatentForceError
from latentforce.priors import SignedNormal, SoftplusNormal


class Carried(NamedTuple):
    """The fitted prior and where it came from (recorded in ``summary.json``)."""

    prior: SoftplusNormal | SignedNormal
    source: str
    param: str
    draws: int
    converged: bool | None


def _softplus_inverse(theta: np.ndarray) -> np.ndarray:
    return theta + np.log(-np.expm1(-theta))


def carried_prior(folder: str | Path, param: str, where: str, *, signed: bool = False) -> Carried:
    """Fit the posterior draws of ``param`` in result ``folder`` (see the module doc).

    ``where`` names the config key in messages; ``signed``: the parameter may
    take either sign. Raises :class:`LatentForceError` for a missing folder or
    file, a parameter that the run did not sample (listing those it did), or
    draws that are not finite (or, for a positive parameter, not positive).
    """
    import xarray as xr

    folder = Path(folder)
    nc = folder / "posterior.nc"
    if not folder.is_dir():
        raise LatentForceError(
            f"{where}: the posterior to carry over is taken from the result folder "
            f"{str(folder)!r}, which does not exist."
        )
    if not nc.is_file():
        raise LatentForceError(
            f"{where}: {str(folder)!r} holds no posterior.nc; give the folder of a finished estimate run."
        )
    try:
        with xr.open_datatree(nc, engine="h5netcdf") as tree:
            post = tree["posterior"].to_dataset() if "posterior" in tree.children else xr.Dataset()
            sampled = [n for n, v in post.data_vars.items() if v.dims == ("chain", "draw")]
            draws = np.asarray(post[param].values, dtype=float).ravel() if param in sampled else None
            # the full post-burn-in chains where the run stored fewer draws than it made (thinned to
            # its stored paths): the fit then sees the whole posterior, not a sub-sample of it
            if draws is not None and "parameter_chains" in tree.children:
                chains = tree["parameter_chains"].to_dataset()
                if param in chains.data_vars:
                    draws = np.asarray(chains[param].values, dtype=float).ravel()
    except (OSError, ValueError, KeyError) as exc:
        raise LatentForceError(f"{where}: {str(nc)!r} cannot be read as a result file ({exc}).") from None
    if draws is None:
        fixed = _fixed_value(folder, param)
        if fixed is not None:
            raise LatentForceError(
                f"{where}: the run in {str(folder)!r} did not infer {param!r}: it was fixed "
                f"at {fixed:g}. Give that number instead, or carry a parameter it sampled."
            )
        names = ", ".join(sampled) if sampled else "none (it sampled no parameter)"
        raise LatentForceError(
            f"{where}: the run in {str(folder)!r} has no posterior draws of {param!r}; "
            f'its sampled parameters are: {names}. Name one with param = "...".'
        )
    if draws.size < 2 or not np.all(np.isfinite(draws)) or not (signed or np.all(draws > 0)):
        raise LatentForceError(
            f"{where}: the draws of {param!r} in {str(nc)!r} are not {'' if signed else 'positive '}finite "
            f"numbers (or fewer than two); they cannot serve as a prior."
        )
    x = draws if signed else _softplus_inverse(draws)
    loc, scale = float(np.mean(x)), float(np.std(x, ddof=1))
    if not (math.isfinite(scale) and scale > 0):
        raise LatentForceError(
            f"{where}: the draws of {param!r} in {str(nc)!r} are all equal; a posterior "
            "with no spread cannot serve as a prior (fix the parameter instead)."
        )
    prior = SignedNormal(loc, scale) if signed else SoftplusNormal(loc, scale)
    return Carried(prior, str(folder.resolve()), param, int(draws.size), _converged(folder))


def _summary(folder: Path) -> dict:
    try:
        return json.loads((folder / "summary.json").read_text())
    except (OSError, ValueError):
        return {}


def _fixed_value(folder: Path, param: str) -> float | None:
    value = _summary(folder).get("fixed", {}).get(param)
    return float(value) if isinstance(value, (int, float)) else None


def _converged(folder: Path) -> bool | None:
    value = _summary(folder).get("converged")
    return bool(value) if isinstance(value, bool) else None
