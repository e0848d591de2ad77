"""Figures of a result folder (``figures/``), drawn from a :class:`RunResult`.

* ``measured.png`` -- each observed channel against time;
* ``displacement.png``, ``velocity.png``, ``force.png`` -- posterior mean with
  shaded 1, 2 and 3 sd bands and the truth in red when known, one subplot
  per DOF / force;
* ``hysteretic_force.png``, ``hysteresis.png`` -- a hysteretic system's
  (Bouc-Wen) internal force against time like a state, and against the
  displacement: the hysteresis loop, with sampled loops and the 90 % band;
* ``output_NAME.png`` -- each virtual sensor (``[[outputs]]``) like a state;
* ``force_psd.png`` -- the posterior force's PSD (mean, 5-95 % band) with the
  GP prior's density at the posterior hyperparameters (and the truth's);
* ``paths.png`` -- a few dozen sampled trajectories per state (cf. Fig. 4,
  Vibration 2020);
* ``traces.png`` -- parameter traces, one colour per chain;
* ``histograms.png`` -- marginal histogram and empirical CDF per parameter
  with the posterior mean and the CDF median (cf. Figs. 1 and 3, ISMA 2018);
* ``joint_hyperparameters.png`` -- 2-D histogram and contours of
  (force_variance, force_lengthscale), the truth as a red x when
  ``result.diagnostics["true_params"]`` gives it; for a kernel sum one per
  term, ``joint_hyperparameters_0.png`` ...

Every figure of a sampling run that did not converge carries "NOT
CONVERGED" across its face and the worst R-hat and ESS at its foot
(:func:`stamp_unconverged`).

Figures are built as bare :class:`matplotlib.figure.Figure` objects and
saved with the Agg renderer, so nothing touches pyplot's global state or
opens a window, and each figure is released once saved.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from latentforce.models import HYPER_NAME

if TYPE_CHECKING:
    from latentforce.results import RunResult

__all__ = [
    "FIGURE_NAMES",
    "draw_figures",
    "plot_measured",
    "plot_state",
    "plot_hysteresis",
    "plot_paths",
    "plot_traces",
    "plot_histograms",
    "plot_joint_hyperparameters",
]

#: Every file name ``draw_figures`` may write (a redraw removes these first).
FIGURE_NAMES: tuple[str, ...] = (
    "measured.png",
    "displacement.png",
    "velocity.png",
    "force.png",
    "hysteretic_force.png",
    "hysteresis.png",
    "paths.png",
    "traces.png",
    "histograms.png",
    "pairs.png",
    "joint_hyperparameters.png",
    "force_psd.png",
)

DPI = 110
_STATES = ("displacement", "velocity", "hysteretic_force", "force")
_STATE_UNITS = {"displacement": "m", "velocity": "m/s", "hysteretic_force": "N", "force": "N"}
_QUANTITY_UNITS = {
    "displacement": "m",
    "velocity": "m/s",
    "acceleration": "m/s$^2$",
    "force": "N",
}
_PARAM_UNITS = {
    "m": "kg",
    "c": "N s/m",
    "k": "N/m",
    "k3": "N/m$^3$",
    "alpha": "N/m",
    "force_variance": "N$^2$",
    "force_lengthscale": "s",
}
_MEAN_COLOUR = "C0"
_TRUTH_COLOUR = "red"


def draw_figures(result: RunResult, fig_dir: Path) -> list[Path]:
    """Draw every figure that ``result`` has data for into ``fig_dir``."""
    fig_dir = Path(fig_dir)
    fig_dir.mkdir(parents=True, exist_ok=True)
    written = []
    if result.observed:
        written.append(plot_measured(result, fig_dir / "measured.png"))
    for state in _STATES:
        if state in result.state_mean:
            written.append(plot_state(result, state, fig_dir / f"{state}.png"))
    if "hysteretic_force" in result.state_mean and "displacement" in result.state_mean:
        written.append(plot_hysteresis(result, fig_dir / "hysteresis.png"))
    for name in result.outputs:
        if name in result.state_mean:
            written.append(plot_state(result, name, fig_dir / f"output_{name}.png"))
    if result.force_psd:
        written.append(plot_force_psd(result, fig_dir / "force_psd.png"))
    if result.path_draws:
        written.append(plot_paths(result, fig_dir / "paths.png"))
    if result.param_draws:
        written.append(plot_traces(result, fig_dir / "traces.png"))
        written.append(plot_histograms(result, fig_dir / "histograms.png"))
        if len(result.param_draws) >= 2:
            written.append(plot_pairs(result, fig_dir / "pairs.png"))
        # one figure per kernel term whose variance and lengthscale are both sampled ("_0", "_1" ...: a sum)
        for term in _hyper_terms(result.param_draws):
            if {f"force_variance{term}", f"force_lengthscale{term}"} <= set(result.param_draws):
                written.append(plot_joint_hyperparameters(result, fig_dir / f"joint_hyperparameters{term}.png", term))
    return written


def _save(fig: Figure, path: Path, result: RunResult) -> Path:
    # room at the foot for the unconverged stamp's line (it sat on the x labels)
    fig.tight_layout(rect=(0.0, 0.035, 1.0, 1.0) if not_converged(result) else None)
    stamp_unconverged(fig, result)
    fig.savefig(path, dpi=DPI)
    fig.clear()
    return Path(path)


def not_converged(result: RunResult) -> bool:
    """A sampling run whose convergence record says no (or that has none); ``kalman`` is exact."""
    if result.method == "kalman":
        return False
    return not (result.convergence or {}).get("converged", False)


def stamp_unconverged(fig: Figure, result: RunResult) -> None:
    """ "NOT CONVERGED" across the face of ``fig`` when the run did not converge, with the
    worst R-hat and ESS: a figure of an unconverged run must say so wherever it is shown."""
    if not not_converged(result):
        return
    record = result.convergence or {}
    fig.text(
        0.5,
        0.5,
        "NOT CONVERGED",
        color="red",
        alpha=0.35,
        fontsize=40,
        fontweight="bold",
        ha="center",
        va="center",
        rotation=20,
        zorder=1000,
    )
    detail = (
        f"max R-hat {record['max_r_hat']:.3f}, min bulk ESS {record['min_ess_bulk']:.0f}"
        if record.get("max_r_hat") is not None and record.get("min_ess_bulk") is not None
        else record.get("reason", "no convergence record")
    )
    fig.text(0.5, 0.01, f"NOT CONVERGED: {detail}", color="red", fontsize=9, ha="center", va="bottom", zorder=1000)


def _columns(array: np.ndarray) -> np.ndarray:
    a = np.asarray(array, dtype=float)
    return a[:, None] if a.ndim == 1 else a


def _component_title(state: str, i: int, width: int) -> str:
    if state not in _STATES:  # a virtual sensor: its own name
        return state
    name = state.replace("_", " ").capitalize()
    if width == 1:
        return name
    where = {"displacement": "DOF", "velocity": "DOF", "hysteretic_force": "element"}.get(state, "force")
    return f"{name}, {where} {i}"


def _state_label(state: str, result: RunResult | None = None) -> str:
    unit = (result.outputs.get(state) if result is not None else None) or _STATE_UNITS.get(state)
    return f"{state} [{unit}]" if unit else state


def _channel_unit(result: RunResult, column: str) -> str:
    """Units of a measured channel: from ``diagnostics["channel_quantities"]``
    (column -> quantity) when the caller recorded it, else from the name."""
    quantities = result.diagnostics.get("channel_quantities") or {}
    quantity = quantities.get(column)
    if quantity is None:
        lowered = column.lower()
        for prefix, name in (("acc", "acceleration"), ("vel", "velocity"), ("disp", "displacement")):
            if lowered.startswith(prefix):
                quantity = name
                break
    return _QUANTITY_UNITS.get(quantity or "", "")


def _hyper_terms(names) -> list[str]:
    """The kernel terms' suffixes among parameter names: ``[""]`` for a Matérn, ``["_0", "_1"]`` for a sum."""
    found = {m.group(2) or "" for n in names if (m := HYPER_NAME.fullmatch(n))}
    return sorted(found, key=lambda t: (len(t), t))


def _param_label(name: str) -> str:
    """``name [unit]`` where the unit is fixed: a storey's ``k_1`` as ``k``, an element's ``element0_k3`` as
    ``k3`` (Bouc-Wen's beta and gamma have none: theirs depends on nu)."""
    m = HYPER_NAME.fullmatch(name)
    key = f"force_{m.group(1)}" if m else re.sub(r"^element\d+_|_\d+$", "", name)
    unit = _PARAM_UNITS.get(key)
    return f"{name} [{unit}]" if unit else name


def _true_params(result: RunResult) -> dict[str, float]:
    true_params = result.diagnostics.get("true_params") or {}
    return {k: float(v) for k, v in true_params.items() if v is not None}


def plot_measured(result: RunResult, path: Path) -> Path:
    """Each observed channel against time, one subplot per channel."""
    n = len(result.observed)
    fig = Figure(figsize=(9, 2.4 * n + 0.6))
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    for ax, (column, values) in zip(axes, result.observed.items()):
        values = np.asarray(values, dtype=float)  # SI
        unit = _channel_unit(result, column)
        known = result.units.get(column) or {}
        if known.get("original") and known.get("scale"):  # in the unit the data came in (mm, g ...)
            values, unit = values / float(known["scale"]), str(known["original"])
        ax.plot(result.time, values, lw=0.7, color="0.2")
        ax.set_ylabel(f"{column} [{unit}]" if unit else column)
        ax.set_title(f"Measured channel '{column}'")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    return _save(fig, path, result)


def plot_state(result: RunResult, state: str, path: Path) -> Path:
    """Posterior mean with 1, 2, 3 sd bands; truth in red when known."""
    mean = _columns(result.state_mean[state])
    sd = _columns(result.state_sd[state])
    truth = _columns(result.truth[state]) if state in result.truth else None
    width = mean.shape[1]
    time = np.asarray(result.time, dtype=float)
    fig = Figure(figsize=(9, 2.8 * width + 0.6))
    axes = fig.subplots(width, 1, sharex=True, squeeze=False)[:, 0]
    for i, ax in enumerate(axes):
        for k, alpha in ((3, 0.12), (2, 0.2), (1, 0.3)):
            ax.fill_between(
                time,
                mean[:, i] - k * sd[:, i],
                mean[:, i] + k * sd[:, i],
                color=_MEAN_COLOUR,
                alpha=alpha,
                lw=0,
                label=f"$\\pm{k}$ sd",
            )
        ax.plot(time, mean[:, i], color=_MEAN_COLOUR, lw=1.0, label="posterior mean")
        if truth is not None:
            ax.plot(time, truth[:, i], color=_TRUTH_COLOUR, lw=0.9, ls="--", label="truth")
        ax.set_ylabel(_state_label(state, result))
        ax.set_title(f"{_component_title(state, i, width)}: posterior ({result.method})")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize="small", ncol=5)
    axes[-1].set_xlabel("time [s]")
    return _save(fig, path, result)


def _loop_abscissae(result: RunResult, width: int):
    """Per hysteretic element, how its displacement is read off the DOFs' displacements: the
    element's DOFs ``(i,)`` or ``(i, j)`` (relative displacement ``z_i - z_j``) from
    ``diagnostics["elements"]`` (MDOF structures), else DOF ``min(e, ndof - 1)``."""
    elements = [(i, e) for i, e in enumerate(result.diagnostics.get("elements", [])) if e["type"] == "bouc-wen"]
    if len(elements) == width:
        return [(i, tuple(e["dofs"])) for i, e in elements]
    return [(None, (min(e, result.ndof - 1),)) for e in range(width)]


def _relative(x: np.ndarray, dofs: tuple) -> np.ndarray:
    """``x[..., i] - x[..., j]`` (or ``x[..., i]``) of an array whose last axis is the DOF."""
    return x[..., dofs[0]] - (x[..., dofs[1]] if len(dofs) > 1 else 0.0)


def plot_hysteresis(result: RunResult, path: Path, max_paths: int = 20) -> Path:
    """The hysteresis loop of each hysteretic element: its force against its displacement (the
    relative displacement of its two DOFs), the posterior mean, up to ``max_paths`` sampled loops,
    the 90 % band of the force (vertical bars) and the truth in red; on the right a zoom on the
    samples around the largest force, where the band is visible."""
    r_mean, r_sd = _columns(result.state_mean["hysteretic_force"]), _columns(result.state_sd["hysteretic_force"])
    z_all = _columns(result.state_mean["displacement"])
    width, T = r_mean.shape[1], r_mean.shape[0]
    fig = Figure(figsize=(11, 4.8 * width))
    axes = fig.subplots(width, 2, squeeze=False)
    draws_r = result.path_draws.get("hysteretic_force")
    draws_z = result.path_draws.get("displacement")
    if draws_r is not None and draws_z is not None:
        draws_r = np.asarray(draws_r, dtype=float).reshape(-1, np.shape(draws_r)[2], width)
        draws_z = np.asarray(draws_z, dtype=float).reshape(-1, np.shape(draws_z)[2], z_all.shape[1])
    truth_z = _columns(result.truth["displacement"]) if "displacement" in result.truth else None
    truth_r = _columns(result.truth["hysteretic_force"]) if "hysteretic_force" in result.truth else None
    for j, (element, dofs) in enumerate(_loop_abscissae(result, width)):
        loop = dict(
            r=r_mean[:, j],
            s=r_sd[:, j],
            z=_relative(z_all, dofs),
            draws=None if draws_z is None else (_relative(draws_z, dofs), draws_r[:, :, j]),
            truth=None if truth_z is None or truth_r is None else (_relative(truth_z, dofs), truth_r[:, j]),
            xlabel=_state_label("displacement", result)
            if len(dofs) == 1 and result.ndof == 1
            else f"displacement {_dofs_name(dofs)}".rstrip() + f" [{_STATE_UNITS['displacement']}]",
        )
        peak = int(np.argmax(np.abs(loop["r"])))
        zoom = slice(max(0, peak - 12), min(T, peak + 13))
        for ax, window, every in ((axes[j, 0], slice(0, T), max(1, T // 150)), (axes[j, 1], zoom, 1)):
            _draw_loop(ax, result, loop, window, every, max_paths)
        title = "Hysteresis loop"
        if element is not None:  # an MDOF structure's element: its place in [[system.elements]] and DOFs
            title += f", element {element} (DOFs {', '.join(map(str, dofs))})"
        elif width > 1:
            title += f", internal state {j}"
        axes[j, 0].set_title(f"{title}: posterior ({result.method})")
        # the zoom: a box around the peak a few bands high, so that the band shows
        z_span = np.ptp(loop["z"]) or 1.0
        r_half = max(8.0 * 1.645 * float(loop["s"][peak]), 0.01 * (np.ptp(loop["r"]) or 1.0))
        # ... and no wider than the zoomed samples reach (at the record's extreme displacement half of the
        # box was empty), with few ticks (their long labels ran into each other)
        near, pad = loop["z"][zoom], 0.005 * z_span
        lo = max(loop["z"][peak] - 0.03 * z_span, float(np.min(near)) - pad)
        hi = min(loop["z"][peak] + 0.03 * z_span, float(np.max(near)) + pad)
        axes[j, 1].set_xlim(lo, hi)
        for ax in axes[j]:
            ax.xaxis.set_major_locator(MaxNLocator(5))
        axes[j, 1].set_ylim(loop["r"][peak] - r_half, loop["r"][peak] + r_half)
        axes[j, 1].set_title(f"zoom on the largest force (t = {float(result.time[peak]):.4g} s)")
        axes[j, 0].legend(loc="upper left", fontsize="small")
    return _save(fig, path, result)


def _dofs_name(dofs: tuple) -> str:
    return f"z{dofs[0]} - z{dofs[1]}" if len(dofs) > 1 else f"z{dofs[0]}"


def _draw_loop(ax, result, loop: dict, window, every, max_paths) -> None:
    from matplotlib.collections import LineCollection

    if loop["draws"] is not None:
        dz, dr = (a[:, window] for a in loop["draws"])
        pick = np.unique(np.linspace(0, dr.shape[0] - 1, min(max_paths, dr.shape[0])).astype(int))
        for k in pick:
            ax.plot(dz[k], dr[k], color="0.55", lw=0.4, alpha=0.4)
        ax.plot([], [], color="0.55", lw=0.8, label=f"{len(pick)} sampled loops")
    z, r, s = loop["z"][window][::every], loop["r"][window][::every], 1.645 * loop["s"][window][::every]
    ax.add_collection(
        LineCollection(np.stack([np.c_[z, r - s], np.c_[z, r + s]], axis=1), colors=_MEAN_COLOUR, alpha=0.4)
    )
    ax.plot([], [], color=_MEAN_COLOUR, alpha=0.4, label="90 % band")
    ax.plot(loop["z"][window], loop["r"][window], color=_MEAN_COLOUR, lw=1.0, label="posterior mean")
    if loop["truth"] is not None:
        ax.plot(loop["truth"][0][window], loop["truth"][1][window], color=_TRUTH_COLOUR, lw=0.8, ls="--", label="truth")
    ax.set_xlabel(loop["xlabel"])
    ax.set_ylabel(_state_label("hysteretic_force", result))
    ax.grid(alpha=0.3)


def plot_paths(result: RunResult, path: Path, max_paths: int = 30) -> Path:
    """Up to ``max_paths`` sampled trajectories per state, spread evenly over
    chains and draws, with the truth in red when known."""
    rows = []
    for state in _STATES + tuple(s for s in result.path_draws if s not in _STATES):
        if state not in result.path_draws:
            continue
        draws = np.asarray(result.path_draws[state], dtype=float)
        if draws.ndim == 3:
            draws = draws[..., None]
        flat = draws.reshape(-1, draws.shape[2], draws.shape[3])
        pick = np.unique(np.linspace(0, flat.shape[0] - 1, min(max_paths, flat.shape[0])).astype(int))
        for i in range(draws.shape[3]):
            rows.append((state, i, draws.shape[3], flat[pick, :, i]))
    time = np.asarray(result.time, dtype=float)
    fig = Figure(figsize=(9, 2.6 * len(rows) + 0.6))
    axes = fig.subplots(len(rows), 1, sharex=True, squeeze=False)[:, 0]
    for ax, (state, i, width, paths) in zip(axes, rows):
        ax.plot(time, paths.T, color="0.35", lw=0.5, alpha=0.35)
        ax.plot([], [], color="0.35", lw=0.8, label=f"{paths.shape[0]} sampled paths")
        if state in result.truth:
            ax.plot(time, _columns(result.truth[state])[:, i], color=_TRUTH_COLOUR, lw=0.9, label="truth")
        ax.set_ylabel(_state_label(state, result))
        ax.set_title(f"{_component_title(state, i, width)}: sampled trajectories ({result.method})")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize="small")
    axes[-1].set_xlabel("time [s]")
    return _save(fig, path, result)


def _chains(result: RunResult) -> dict:
    """Each sampled parameter's full post-burn-in chains (``param_chains``), or the draws stored
    beside the trajectories where the run kept no others."""
    return {n: result.param_chains.get(n, d) for n, d in result.param_draws.items()}


def plot_traces(result: RunResult, path: Path) -> Path:
    """Trace of each sampled parameter, one colour per chain."""
    chains = _chains(result)
    names = list(chains)
    truth = _true_params(result)
    fig = Figure(figsize=(9, 2.2 * len(names) + 0.6))
    axes = fig.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0]
    for ax, name in zip(axes, names):
        draws = np.atleast_2d(np.asarray(chains[name], dtype=float))
        for chain, trace in enumerate(draws):
            ax.plot(trace, lw=0.6, color=f"C{chain % 10}", alpha=0.8, label=f"chain {chain}")
        if name in truth:
            ax.axhline(truth[name], color=_TRUTH_COLOUR, lw=1.0, ls="--", label="truth")
        ax.set_ylabel(_param_label(name))
        ax.set_title(f"Trace of {name}")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize="small", ncol=min(6, len(axes[0].lines)))
    axes[-1].set_xlabel("draw (after burn-in)")
    return _save(fig, path, result)


def plot_histograms(result: RunResult, path: Path) -> Path:
    """Marginal histogram and empirical CDF per parameter, with the posterior
    mean, the CDF median (where the ECDF crosses 1/2) and the truth if known."""
    chains = _chains(result)
    names = list(chains)
    truth = _true_params(result)
    fig = Figure(figsize=(10, 2.8 * len(names) + 0.6))
    axes = fig.subplots(len(names), 2, squeeze=False)
    for (ax_hist, ax_cdf), name in zip(axes, names):
        samples = np.sort(np.asarray(chains[name], dtype=float).ravel())
        samples = samples[np.isfinite(samples)]
        mean, median = float(np.mean(samples)), float(np.median(samples))
        ax_hist.hist(samples, bins=_bins(samples.size), density=True, color="0.6", edgecolor="0.35")
        ecdf = np.arange(1, samples.size + 1) / samples.size
        ax_cdf.step(samples, ecdf, where="post", color="0.2", lw=1.0)
        ax_cdf.axhline(0.5, color="0.5", lw=0.6, ls=":")
        for ax in (ax_hist, ax_cdf):
            ax.axvline(mean, color=_MEAN_COLOUR, lw=1.2, label=f"mean {mean:.4g}")
            ax.axvline(median, color="C2", lw=1.2, ls="--", label=f"CDF median {median:.4g}")
            if name in truth:
                ax.axvline(truth[name], color=_TRUTH_COLOUR, lw=1.2, ls=":", label=f"truth {truth[name]:.4g}")
            ax.set_xlabel(_param_label(name))
            ax.grid(alpha=0.3)
        ax_hist.set_ylabel("density")
        ax_hist.set_title(f"Posterior of {name}")
        ax_hist.legend(fontsize="small")
        ax_cdf.set_ylabel("empirical CDF")
        ax_cdf.set_ylim(0, 1.02)
        ax_cdf.set_title(f"Empirical CDF of {name}")
    return _save(fig, path, result)


def _bins(n: int) -> int:
    return int(np.clip(np.sqrt(max(n, 1)), 10, 60))


def plot_joint_hyperparameters(result: RunResult, path: Path, term: str = "") -> Path:
    """Joint 2-D histogram with contours of the force variance and lengthscale (of the kernel
    sum's term ``term``, ``"_0"``, ``"_1"`` ..., if given)."""
    var, ls = f"force_variance{term}", f"force_lengthscale{term}"
    chains = _chains(result)
    x = np.asarray(chains[ls], dtype=float).ravel()
    y = np.asarray(chains[var], dtype=float).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    fig = Figure(figsize=(6.4, 5.4))
    ax = fig.subplots()
    bins = _bins(x.size) // 2 + 5
    counts, x_edges, y_edges, image = ax.hist2d(x, y, bins=bins, cmap="Greys")
    fig.colorbar(image, ax=ax, label="draws per bin")
    if np.count_nonzero(counts) > 1 and counts.max() > counts[counts > 0].min():
        x_mid = 0.5 * (x_edges[1:] + x_edges[:-1])
        y_mid = 0.5 * (y_edges[1:] + y_edges[:-1])
        ax.contour(x_mid, y_mid, counts.T, levels=5, colors=_MEAN_COLOUR, linewidths=0.8)
    truth = _true_params(result)
    if ls in truth and var in truth:
        ax.plot(
            truth[ls],
            truth[var],
            "x",
            color=_TRUTH_COLOUR,
            ms=12,
            mew=2.5,
            label="truth",
        )
        ax.legend(loc="upper right")
    ax.set_xlabel(_param_label(ls))
    ax.set_ylabel(_param_label(var))
    which = f" (kernel term {term[1:]})" if term else ""
    ax.set_title(f"Joint posterior of the force hyperparameters{which}")
    return _save(fig, path, result)


#: parameters in the pair plot at most (the first ones in the result's order)
PAIRS_MAX = 8


def plot_pairs(result: RunResult, path: Path) -> Path:
    """Pair plot of the sampled parameters: each one's histogram on the diagonal, each pair's joint
    2-D histogram below it (a ridge shows a pair the data trade against each other), truth marked."""
    chains = _chains(result)
    names = list(chains)[:PAIRS_MAX]
    truth = _true_params(result)
    samples = {n: np.asarray(chains[n], dtype=float).ravel() for n in names}
    n = len(names)
    fig = Figure(figsize=(2.3 * n + 0.8, 2.3 * n + 0.6))
    axes = fig.subplots(n, n, squeeze=False)
    for i, yname in enumerate(names):
        for j, xname in enumerate(names):
            ax = axes[i, j]
            if j > i:
                ax.set_axis_off()
                continue
            x = samples[xname]
            if i == j:
                ok = np.isfinite(x)
                ax.hist(x[ok], bins=_bins(int(ok.sum())), color="0.6", edgecolor="0.35")
                if xname in truth:
                    ax.axvline(truth[xname], color=_TRUTH_COLOUR, lw=1.2, ls=":")
                ax.set_yticks([])
            else:
                y = samples[yname]
                ok = np.isfinite(x) & np.isfinite(y)
                ax.hist2d(x[ok], y[ok], bins=_bins(int(ok.sum())) // 2 + 5, cmap="Greys")
                if xname in truth and yname in truth:
                    ax.plot(truth[xname], truth[yname], "x", color=_TRUTH_COLOUR, ms=8, mew=2)
            if i == n - 1:
                ax.set_xlabel(_param_label(xname), fontsize="small")
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(_param_label(yname), fontsize="small")
            elif j > 0:
                ax.set_yticklabels([])
            ax.tick_params(labelsize="x-small")
    more = len(chains) - n
    fig.suptitle("Pairs of sampled parameters" + (f" (the first {n}; {more} more not shown)" if more > 0 else ""))
    return _save(fig, path, result)


def plot_force_psd(result: RunResult, path: Path) -> Path:
    """The posterior force's one-sided PSD: mean over posterior paths with the 5-95 % band,
    the GP prior's density at the posterior hyperparameters, and the truth's when known."""
    table = result.force_psd
    freq = np.asarray(table["frequency"], dtype=float)
    keep = freq > 0  # log axes
    suffixes = [k[len("psd_mean") :] for k in table if k.startswith("psd_mean")]
    fig = Figure(figsize=(8, 3.4 * len(suffixes) + 0.6))
    axes = fig.subplots(len(suffixes), 1, sharex=True, squeeze=False)[:, 0]
    for ax, sfx in zip(axes, suffixes):
        ax.fill_between(
            freq[keep],
            table[f"psd_q05{sfx}"][keep],
            table[f"psd_q95{sfx}"][keep],
            color=_MEAN_COLOUR,
            alpha=0.25,
            lw=0,
            label="posterior 5-95 %",
        )
        ax.loglog(freq[keep], table[f"psd_mean{sfx}"][keep], color=_MEAN_COLOUR, lw=1.0, label="posterior mean")
        if np.all(np.isfinite(table["prior_psd"])):
            ax.loglog(
                freq[keep],
                table["prior_psd"][keep],
                color="k",
                lw=1.0,
                ls="--",
                label="GP prior at posterior hyperparameters",
            )
        if f"truth_psd{sfx}" in table:
            ax.loglog(
                freq[keep], table[f"truth_psd{sfx}"][keep], color=_TRUTH_COLOUR, lw=0.9, ls=":", label="truth (Welch)"
            )
        ax.set_ylabel("PSD [N$^2$/Hz]")
        which = "" if not sfx else f", force {sfx[1:]}"
        ax.set_title(f"Force spectrum{which}: one-sided Welch density ({result.method})")
        ax.grid(alpha=0.3, which="both")
        ax.legend(loc="lower left", fontsize="small")
    axes[-1].set_xlabel("frequency [Hz]")
    return _save(fig, path, result)
