r"""``latentforce demo silverbox``: real measurements, the field workflow.

The Silverbox benchmark (Wigren & Schoukens 2013; ``demos/data/README.md``)
is an electronic circuit that realises a forced Duffing oscillator,
:math:`m\ddot y + c\dot y + k y + k_3 y^3 = u`, with its input :math:`u`
(the force) and output :math:`y` (the displacement) both measured, in volts,
at :math:`f_s = 10^7/2^{14} \approx 610` Hz: the one public record where an
input estimated from the response can be checked against the true input.

1. **Calibration** (``calibration/``): one multisine realisation with the
   input measured, as a load cell would (``quantity = "force"``), and the
   output as displacement; m, c, k, k3, both noise levels and the force's
   hyperparameters inferred (method ``ukf``: random-walk and independence
   Metropolis on the unscented Kalman filter's likelihood, the states mixed
   over the draws). The same with a linear model (``kalman-mcmc``,
   ``calibration-linear/``).
2. **Monitoring** (``arrow-low/``, ``arrow-mid/``, ``arrow-high/``): windows
   of the "arrow" (band-limited noise of growing amplitude), the output
   alone, the parameters' priors carried from the calibration
   (``prior = "posterior"``), the force's hyperparameters inferred afresh.
   The measured input sits in the data as the ``force`` column, the truth
   the summary scores against; the linear model's run is in ``linear/``.
3. Baselines with the calibration's posterior medians: the inverse problem
   solved directly, :math:`\hat u = m\ddot y + c\dot y + ky + k_3y^3`, with the
   derivatives by central differences and by the FFT (exact for a signal
   band-limited below Nyquist, as this one is), each computed with 256
   samples of the record on either side of the window.

Writes ``silverbox.md`` (the table) and ``figures/`` (input against the
measured one, whole window and a zoom; the identified restoring force
against displacement) in the demo folder. ``--quick``: a 512-sample
calibration and the high-amplitude window cut to 512 samples.
"""

from __future__ import annotations

import time
from importlib import resources
from pathlib import Path

import numpy as np

from latentforce.demos.common import preload_modules, run_cases_concurrently, table, write_case
from latentforce.results import check_out_dir, coverage, nmse

FS = 1.0e7 / 2**14  # Hz, the benchmark's sample rate
#: First sample of the first multisine realisation (after the zero-input gap that
#: ends the arrow, samples 40 502-40 578) plus 300 samples of its start-up transient.
CALIBRATION_START = 40_579 + 300
#: First samples of the arrow windows, low, middle and high amplitude (the
#: arrow's amplitude grows linearly from sample 0 to about 40 500).
ARROW = {"low": 8_000, "mid": 20_000, "high": 36_000}
WINDOW, QUICK_WINDOW = 4096, 512
CALIBRATION, QUICK_CALIBRATION = 2048, 512
MARGIN = 256  # samples of the record on either side of a window for the inversion baselines
#: Weakly informative priors, from the circuit's order of magnitude (a static
#: gain of about 1 V/V and a resonance near 70 Hz: k ~ 1, m = k / (2 pi 70)^2 ~ 5e-6,
#: a damping ratio of a few per cent); each a factor e either way at 1 sd.
SYSTEM_PRIORS = {
    "m": {"prior": "lognormal", "mu": -12.2, "sigma": 1.0},
    "c": {"prior": "lognormal", "mu": -8.5, "sigma": 1.0},
    "k": {"prior": "lognormal", "mu": 0.0, "sigma": 1.0},
    "k3": {"prior": "lognormal", "mu": 1.0, "sigma": 1.5},
}
NOISE_PRIOR = {"prior": "lognormal", "mu": -7.0, "sigma": 2.0}  # V: ~1 mV, a factor 7 either way
FORCE = {
    "kernel": "matern32",
    "variance": {"prior": "lognormal", "mu": -7.0, "sigma": 2.0},
    "lengthscale": {"prior": "lognormal", "mu": -6.0, "sigma": 2.0},
}


def load() -> tuple[np.ndarray, np.ndarray]:
    """The benchmark's input and output voltages ``(u, y)``, each less its mean (DC offsets).

    The bundled copy (``demos/data/silverbox.npz``) holds the original file's
    two columns as float32 (the original is printed with 5 significant digits).
    """
    with resources.files("latentforce.demos").joinpath("data/silverbox.npz").open("rb") as f:
        d = np.load(f)
        u, y = d["V1"].astype(float), d["V2"].astype(float)
    return u - u.mean(), y - y.mean()


def _columns(y: np.ndarray, u: np.ndarray, *, measured_input: bool) -> dict:
    t = np.arange(len(y)) / FS
    return {"time": t, "y": y, ("u" if measured_input else "force"): u}


def _sensor(column: str, quantity: str, noise) -> dict:
    return {"column": column, "quantity": quantity, "dof": 0, "noise_std": noise}


def _inference(method: str, seed: int, quick: bool = False) -> dict:
    # --quick: a shorter warm-up (the chains start from the Laplace fit, with independence steps
    # from it, so 200 iterations adapt them; the default is 500)
    return {"method": method, "chains": 4, "seed": seed, **({"burn_in": 200} if quick else {})}


def calibration_config(linear: bool, seed: int, quick: bool = False) -> dict:
    """Input as a load cell, output as displacement; every parameter inferred."""
    system = {k: v for k, v in SYSTEM_PRIORS.items() if not (linear and k == "k3")}
    return {
        "data": {"time_column": "time"},
        "system": {"type": "linear" if linear else "duffing", **system},
        "force": FORCE,
        "sensors": [_sensor("u", "force", NOISE_PRIOR), _sensor("y", "displacement", NOISE_PRIOR)],
        "inference": _inference("kalman-mcmc" if linear else "ukf", seed, quick),
    }


def monitoring_config(calibration: str, linear: bool, seed: int, quick: bool = False, y=None) -> dict:
    """Output alone; the structure's parameters and the output's noise carried from ``calibration``.

    A window of the arrow starts in motion, and a nonlinear system's default first state is near rest
    (the run's check says so: its first period missed the filter's predictions by 3.5x their spread):
    given the window's output ``y``, the Duffing's ``[initial]`` is zero-mean with sds of three times the
    window's rms displacement and velocity (the force states' entries are not used: they start from
    their stationary GP distribution). The linear system's default start is already stationary."""
    carried = {"prior": "posterior", "from": calibration}
    names = ("m", "c", "k") if linear else ("m", "c", "k", "k3")
    config = {
        "data": {"time_column": "time"},
        "system": {"type": "linear" if linear else "duffing", **{n: dict(carried) for n in names}},
        "force": FORCE,
        "sensors": [_sensor("y", "displacement", dict(carried, param="noise_std_y"))],
        "inference": _inference("kalman-mcmc" if linear else "ukf", seed, quick),
    }
    if not linear and y is not None:
        rms = [float(np.sqrt(np.mean(np.square(v)))) for v in (y, np.gradient(y, 1.0 / FS))]
        config["initial"] = {"mean": [0.0] * 4, "sd": [3.0 * rms[0], 3.0 * rms[1], 1.0, 1.0]}
    return config


def inversion(y: np.ndarray, params: dict, spectral: bool) -> np.ndarray:
    r""":math:`\hat u = m\ddot y + c\dot y + k y + k_3 y^3` from the measured output: derivatives by
    central differences (one-sided at the ends) or by the FFT (``spectral``)."""
    dt = 1.0 / FS
    if spectral:
        n = len(y)
        w = 2j * np.pi * np.fft.rfftfreq(n, dt)
        Y = np.fft.rfft(y)
        v, a = np.fft.irfft(w * Y, n), np.fft.irfft(w**2 * Y, n)
    else:
        v = np.gradient(y, dt)
        a = np.gradient(v, dt)
        a[1:-1] = (y[2:] - 2.0 * y[1:-1] + y[:-2]) / dt**2
    return params["m"] * a + params["c"] * v + params["k"] * y + params.get("k3", 0.0) * y**3


def _scores(u: np.ndarray, mean: np.ndarray, sd: np.ndarray | None) -> dict:
    out = {"nmse": nmse(u, mean)}
    if sd is not None:
        out.update(cov1=coverage(u, mean, sd, 1.0), cov3=coverage(u, mean, sd, 3.0))
    return out


def _result_row(label: str, method: str, u: np.ndarray, result, seconds: float) -> list[str]:
    s = _scores(u, result.state_mean["force"][:, 0], result.state_sd["force"][:, 0])
    conv = result.convergence or {}
    r_hat = conv.get("max_r_hat")
    flag = "" if conv.get("converged", True) else " (NOT CONVERGED)"
    return [
        label,
        method,
        f"{s['nmse']:.2f}",
        f"{100 * s['cov1']:.1f}",
        f"{100 * s['cov3']:.1f}",
        (f"{r_hat:.3f}" if r_hat is not None else "-") + flag,
        f"{seconds:.0f}",
    ]


def _baseline_rows(label: str, y_all: np.ndarray, window: slice, u: np.ndarray, params: dict) -> list[list[str]]:
    """The inversions on the window, computed with ``MARGIN`` samples of the record on either side
    (cut off before scoring): the FFT's periodic extension and the one-sided end differences
    then do not touch the scored samples, as when an engineer inverts a whole record."""
    lo = max(0, window.start - MARGIN)
    y = y_all[lo : window.stop + MARGIN]
    cut = slice(window.start - lo, window.start - lo + (window.stop - window.start))
    rows = []
    for name, spectral in (("inversion, central differences", False), ("inversion, FFT derivatives", True)):
        rows.append([label, name, f"{nmse(u, inversion(y, params, spectral)[cut]):.2f}", "-", "-", "-", "0"])
    return rows


def _medians(result) -> dict:
    summary = result.param_summary or {}
    if summary:
        return {n: float(s["median"]) for n, s in summary.items()}
    return {n: float(np.median(d)) for n, d in result.param_draws.items()}


def run_silverbox(
    out: Path,
    quick: bool = False,
    seed: int = 0,
    overwrite: bool = False,
    echo=print,
    progress=None,
    paper_settings: bool = False,
) -> None:
    del progress, paper_settings  # several runs side by side: no single progress bar
    out = Path(out)
    check_out_dir(out, overwrite)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    preload_modules()
    u_all, y_all = load()
    n_cal = QUICK_CALIBRATION if quick else CALIBRATION
    n_win = QUICK_WINDOW if quick else WINDOW
    windows = {"high": ARROW["high"]} if quick else dict(ARROW)
    echo(
        f"Silverbox (Wigren & Schoukens 2013): a circuit realising m y'' + c y' + k y + k3 y^3 = u, "
        f"input and output measured at {FS:.2f} Hz"
    )
    cal = slice(CALIBRATION_START, CALIBRATION_START + n_cal)
    cal_cols = _columns(y_all[cal], u_all[cal], measured_input=True)
    echo(
        f"1. calibration on {n_cal} samples of a multisine realisation (input measured): "
        "Duffing (ukf) and linear (kalman-mcmc) ..."
    )
    cal_jobs = [
        lambda: _timed(
            write_case, out / "calibration", calibration_config(False, seed, quick), cal_cols, overwrite=True, seed=seed
        ),
        lambda: _timed(
            write_case,
            out / "calibration-linear",
            calibration_config(True, seed, quick),
            cal_cols,
            overwrite=True,
            seed=seed,
        ),
    ]
    (cal_nl, s_nl), (cal_lin, s_lin) = run_cases_concurrently(cal_jobs)
    params = _medians(cal_nl[2])
    _echo_calibration(echo, cal_nl[2], cal_lin[2], s_nl, s_lin)

    rows, figure_cases = [], []
    for name, start in windows.items():
        sl = slice(start, start + n_win)
        y, u = y_all[sl], u_all[sl]
        cols = _columns(y, u, measured_input=False)
        echo(
            f"2. arrow window '{name}' (samples {start}-{start + n_win - 1}, input rms {u.std():.4f} V): "
            "the input from the output alone ..."
        )
        folder = out / f"arrow-{name}"
        jobs = [
            lambda: _timed(
                write_case,
                folder,
                monitoring_config("../calibration/", False, seed, quick, y),
                cols,
                overwrite=True,
                seed=seed,
            ),
            lambda: _timed(
                write_case,
                folder / "linear",
                monitoring_config("../../calibration-linear/", True, seed, quick),
                cols,
                overwrite=True,
                seed=seed,
            ),
        ]
        (res_nl, sec_nl), (res_lin, sec_lin) = run_cases_concurrently(jobs)
        rows.append(_result_row(name, "Duffing, ukf", u, res_nl[2], sec_nl))
        rows.append(_result_row(name, "linear, kalman-mcmc", u, res_lin[2], sec_lin))
        rows.extend(_baseline_rows(name, y_all, sl, u, params))
        figure_cases.append((name, y, u, res_nl[2]))
    header = ["window", "method", "force NMSE %", "within 1 sd %", "within 3 sd %", "worst R-hat", "s"]
    text = table(rows, header)
    echo("\n" + text)
    _write_table(out / "silverbox.md", rows, header, quick, n_cal, n_win, params)
    from latentforce.demos.silverbox_figures import input_figure, restoring_force_figure

    for name, y, u, result in figure_cases:
        input_figure(out / "figures" / f"input_{name}.png", result, u, name)
    restoring_force_figure(out / "figures" / "restoring_force.png", cal_nl[2], cal_cols["y"], cal_cols["u"], FS)
    echo(f"done in {time.perf_counter() - t0:.1f} s; results in {out}/ (table: {out / 'silverbox.md'})")


def _timed(fn, *args, **kwargs):
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t


def _echo_calibration(echo, nl, lin, s_nl: float, s_lin: float) -> None:
    rows = []
    for label, result, seconds in (("Duffing (ukf)", nl, s_nl), ("linear (kalman-mcmc)", lin, s_lin)):
        summary = result.param_summary or {}
        conv = result.convergence or {}
        for n, s in summary.items():
            rows.append(
                [
                    label,
                    n,
                    f"{s['median']:.4g}",
                    f"[{s['q05']:.4g}, {s['q95']:.4g}]",
                    f"{s['r_hat']:.3f}" if s.get("r_hat") is not None else "-",
                ]
            )
        echo(f"   {label}: {'converged' if conv.get('converged') else 'NOT CONVERGED'} in {seconds:.0f} s")
    echo(table(rows, ["model", "parameter", "median", "90% interval", "R-hat"]))


def _write_table(path: Path, rows, header, quick: bool, n_cal: int, n_win: int, params: dict) -> None:
    lines = [
        "# Silverbox: the input recovered from the output" + (" (--quick)" if quick else ""),
        "",
        f"Calibration: {n_cal} samples of the first multisine realisation, input measured. "
        f"Windows of the arrow: {n_win} samples, output only, parameters carried from the calibration. "
        "Scores against the measured input. Inversion baselines with the calibration's medians: "
        + ", ".join(f"{k} = {v:.4g}" for k, v in params.items() if k in ("m", "c", "k", "k3"))
        + ".",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
    ]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
