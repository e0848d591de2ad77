r"""Does the model fit the data? One-step prediction errors of the exact Kalman filter.

Under the model each channel's one-step prediction error, divided by the sd the filter predicts
for it, is a standard normal (the innovations of a linear-Gaussian model are independent,
:math:`v_t \sim N(0, S_t)`; assimilating the channels one at a time, Kalman's sequential form,
makes each channel's its own scalar). Their mean square is 1 to within
:math:`\sqrt{2/n}` over :math:`n` samples. A mean square far from 1 says the configured model
cannot have made the data: a channel's unit (g read as m/s²), its ``noise_std``, or the force's
variance or the structure's parameters are off. ``method = "kalman"`` runs at fixed parameters
and is exact, so it reports this (``diagnostics.prediction_errors``) and warns beyond a factor
of 4 either way in the mean square (2 in rms).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.compile import jit
from latentforce.inference.kalman import update_channels
from latentforce.inference.kalman_mcmc import linear_gaussian, program_arguments
from latentforce.linalg import symmetrise

#: mean squared standardised prediction error outside [1/LIMIT, LIMIT]: a warning
LIMIT = 4.0


def standardised_innovations(A, Q, H, R, m0, P0, y, mask):
    """``(T, d)`` squared one-step prediction errors over their predicted variances, channel by
    channel in the filter's sequential order; NaN where a channel is not observed."""

    def _step(carry, inputs):
        y_t, mask_t = inputs
        m, P, z2, _ = update_channels(*carry, H, R, y_t, mask_t)
        return (A @ m, symmetrise(A @ P @ A.T + Q)), jnp.where(mask_t, z2, jnp.nan)

    _, z2 = jax.lax.scan(_step, (m0, P0), (jnp.where(mask, y, 0.0), mask))
    return z2


@functools.partial(jit, static_argnames=("model", "dt"))
def _mean_squares(params, y, mask, initial, *, model, dt):
    z2 = standardised_innovations(*linear_gaussian(model, params, dt, initial), y, mask)
    return jnp.nanmean(z2, axis=0)


def prediction_errors(model, params: dict, y, mask, dt: float, initial=None) -> dict[str, float]:
    """Each channel's mean squared standardised one-step prediction error (1 where the model fits)."""
    ms = _mean_squares(*program_arguments(model, params, y, mask), initial, model=model, dt=float(dt))
    return {s.name: float(v) for s, v in zip(model.sensors, np.asarray(ms))}


def warning(errors: dict[str, float]) -> str | None:
    """The warning for the channels whose mean square is off by more than :data:`LIMIT`, or None."""
    high = {c: v for c, v in errors.items() if v > LIMIT}
    low = {c: v for c, v in errors.items() if 0 < v < 1.0 / LIMIT}
    if not high and not low:
        return None
    parts = []
    if high:
        parts.append(
            f"{', '.join(f'{c!r} ({np.sqrt(v):.3g} times)' for c, v in high.items())}: the data vary more than "
            "the model predicts (a noise_std too small, a force variance too small, a unit too large, or "
            "wrong structural parameters)"
        )
    if low:
        parts.append(
            f"{', '.join(f'{c!r} ({np.sqrt(v):.3g} times)' for c, v in low.items())}: the data vary less than the "
            "model predicts (a noise_std or force variance too large, or a unit too small: g read as m/s^2?)"
        )
    return (
        "the model does not fit the data: the one-step prediction errors of the channels "
        + "; ".join(parts)
        + ", in rms over the spread the Kalman filter predicts for them (1 where the model fits; "
        "diagnostics.prediction_errors). Check the channels' units, noise_std and the [force] variance."
    )
