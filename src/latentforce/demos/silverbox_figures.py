"""The Silverbox demo's own figures: the recovered input against the measured one, and the
identified restoring force against displacement (:mod:`latentforce.demos.silverbox`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from latentforce.plots import stamp_unconverged
from latentforce.results import FIGURE_LOCK

ZOOM_S = 0.08  # seconds shown in the zoom (about five periods at the 70 Hz resonance)


def input_figure(path: Path, result, u: np.ndarray, name: str) -> None:
    """Measured input against the posterior mean with its +-3 sd band: the whole window, its error
    against the band, and a zoom."""
    from matplotlib.figure import Figure

    t = result.time
    m, s = result.state_mean["force"][:, 0], result.state_sd["force"][:, 0]
    fig = Figure(figsize=(10, 8.5))
    axes = fig.subplots(3, 1)
    mid = t[len(t) // 2]
    err = axes[1]  # the error, where the whole window's bands can be seen
    err.fill_between(t, -3 * s, 3 * s, color="tab:blue", alpha=0.3, lw=0, label="±3 sd")
    err.plot(t, m - u, color="k", lw=0.4, label="posterior mean - measured")
    err.set_ylabel("error [V]")
    err.legend(fontsize=8, loc="upper left", ncols=2)
    for ax, span in zip(axes[::2], (None, (mid - ZOOM_S / 2, mid + ZOOM_S / 2))):
        sel = slice(None) if span is None else (t >= span[0]) & (t <= span[1])
        ax.fill_between(
            t[sel], (m - 3 * s)[sel], (m + 3 * s)[sel], color="tab:blue", alpha=0.3, lw=0, label="posterior ±3 sd"
        )
        ax.plot(t[sel], u[sel], color="k", lw=0.9 if span else 0.5, label="measured input")
        ax.plot(t[sel], m[sel], color="tab:blue", lw=0.9 if span else 0.5, ls="--", label="posterior mean")
        ax.set_ylabel("input u [V]")
        if span is not None:
            ax.plot(t[sel], u[sel], "k.", ms=3)
    axes[0].set_title(f"Silverbox, arrow window '{name}': input from the output alone", fontsize=10)
    axes[2].set_title(f"zoom: {ZOOM_S * 1e3:.0f} ms in the middle (dots: samples)", fontsize=9, loc="left")
    axes[2].set_xlabel("time in the window [s]")
    axes[0].legend(fontsize=8, loc="upper left", ncols=3)
    stamp_unconverged(fig, result)
    _save(fig, path)


def restoring_force_figure(path: Path, calibration, y: np.ndarray, u: np.ndarray, fs: float) -> None:
    r"""The identified restoring force :math:`k z + k_3 z^3` with its 90 % band over the calibration's
    parameter draws, against the one implied by the measurements, :math:`u - m\ddot y - c\dot y`
    (derivatives by the FFT, the calibration's median m and c)."""
    from matplotlib.figure import Figure

    draws = {n: np.asarray(calibration.param_draws[n]).ravel() for n in ("m", "c", "k", "k3")}
    z = np.linspace(-1.05, 1.05, 201) * np.max(np.abs(y))
    r = draws["k"][:, None] * z + draws["k3"][:, None] * z**3
    lo, med, hi = np.percentile(r, [5, 50, 95], axis=0)
    n = len(y)
    w = 2j * np.pi * np.fft.rfftfreq(n, 1.0 / fs)
    Y = np.fft.rfft(y)
    v, a = np.fft.irfft(w * Y, n), np.fft.irfft(w**2 * Y, n)
    implied = u - np.median(draws["m"]) * a - np.median(draws["c"]) * v
    fig = Figure(figsize=(7, 5))
    ax = fig.subplots()
    ax.plot(y, implied, ".", color="0.6", ms=2, label=r"measured: $u - m\ddot y - c\dot y$")
    ax.fill_between(z, lo, hi, color="tab:red", alpha=0.3, lw=0, label="identified, 90 % band")
    ax.plot(z, med, color="tab:red", lw=1.2, label=r"identified $k z + k_3 z^3$ (median)")
    ax.plot(z, np.median(draws["k"]) * z, color="k", lw=0.8, ls=":", label="its linear part")
    ax.set_xlabel("displacement (output) y [V]")
    ax.set_ylabel("restoring force [V]")
    ax.set_title("Silverbox: restoring force identified in the calibration", fontsize=10)
    ax.legend(fontsize=8)
    stamp_unconverged(fig, calibration)
    _save(fig, path)


def _save(fig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with FIGURE_LOCK:  # matplotlib's text layout is not thread-safe (results.write_results)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
