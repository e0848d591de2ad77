"""Matrices and the initial state of a config: square, symmetric, (semi-)definite checks and the
``[initial]`` table (split from ``io/config.py``; every error names the key)."""

from __future__ import annotations

import numpy as np

from latentforce.io.schema import _Fail, _InitialSection
from latentforce.models import LatentForceModel


def _matrix(fail: _Fail, key: str, rows: list[list[float]]) -> np.ndarray:
    n = len(rows)
    if n == 0 or any(len(r) != n for r in rows):
        raise fail(key, f"must be a square matrix (a list of {n} rows of {n} numbers each).")
    return np.asarray(rows, dtype=float)


def _check_psd(fail: _Fail, key: str, A: np.ndarray, name: str, definite: bool) -> None:
    scale = max(float(np.abs(A).max()), np.finfo(float).tiny)
    if not np.allclose(A, A.T, rtol=0.0, atol=1e-10 * scale):
        raise fail(key, f"the {name} matrix must be symmetric.")
    eig = np.linalg.eigvalsh(A)
    if definite and not eig.min() > 0:
        raise fail(key, f"the {name} matrix must be positive definite (smallest eigenvalue {eig.min():.6g}).")
    if not definite and eig.min() < -1e-10 * scale:
        raise fail(key, f"the {name} matrix must be positive semi-definite (smallest eigenvalue {eig.min():.6g}).")


def _initial_state(section: _InitialSection, model: LatentForceModel, kernel, fail):
    """``(mean, cov)`` of the first state from ``[initial]``: ``mean`` with ``sd`` (independent
    states) or ``cov`` (a full covariance matrix, symmetric positive semi-definite)."""
    layout = (
        f"{model.ndof} displacement(s), {model.ndof} velocity(ies), then "
        f"{model.nforce} x {kernel.dim} force state(s) of the {kernel.name} kernel"
    )
    n = model.n_state
    if (section.sd is None) == (section.cov is None):
        raise fail(
            "[initial]",
            "give either sd (a list of standard deviations) or cov (a full "
            f"{n} x {n} covariance matrix, a list of rows), not "
            f"{'both' if section.sd is not None else 'neither'}.",
        )
    lengths = {"mean": len(section.mean)}
    if section.sd is not None:
        lengths["sd"] = len(section.sd)
    else:
        lengths["cov"] = len(section.cov)
        for i, row in enumerate(section.cov):
            if len(row) != n:
                raise fail(f"[initial].cov[{i}]", f"has {len(row)} entries but the state vector has {n}: {layout}.")
    for name, got in lengths.items():
        if got != n:
            raise fail(f"[initial].{name}", f"has {got} entries but the state vector has {n}: {layout}.")
    mean = np.asarray(section.mean, dtype=float)
    if section.sd is not None:
        return mean, np.diag(np.asarray(section.sd, dtype=float) ** 2)
    cov = np.asarray(section.cov, dtype=float)
    if not np.all(np.isfinite(cov)):
        raise fail("[initial].cov", "holds a value that is not a finite number.")
    scale = max(float(np.max(np.abs(cov))), np.finfo(float).tiny)
    asym = float(np.max(np.abs(cov - cov.T)))
    if asym > 1e-10 * scale:
        raise fail("[initial].cov", f"is not symmetric (largest |cov[i][j] - cov[j][i]| = {asym:.3g}).")
    low = float(np.min(np.linalg.eigvalsh(0.5 * (cov + cov.T))))
    if low < -1e-10 * scale:
        raise fail(
            "[initial].cov",
            f"is not positive semi-definite (smallest eigenvalue {low:.3g}); "
            "a covariance matrix must have no negative eigenvalue.",
        )
    return mean, 0.5 * (cov + cov.T)
