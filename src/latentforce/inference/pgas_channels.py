"""The channels a PGAS run observes through: runs whose models differ only in their sensors share
one structure, hence every compiled program (:func:`observe_through`, :func:`_unnamed`)."""

from __future__ import annotations

import numpy as np


def observe_through(model, channels, y, mask):
    """``(model, y, mask)`` with the channels ``channels``, ``(quantity, dof)`` pairs, in that order.

    Each sensor moves to the channel of its quantity and DOF, with its noise;
    a channel no sensor reads gets a sensor of unit noise that is never
    observed (``y`` NaN, ``mask`` False there), which leaves the likelihood,
    hence the posterior, unchanged.
    """
    from latentforce.models import LatentForceModel, Sensor

    channels = [(str(q), int(d)) for q, d in channels]
    if len(set(channels)) != len(channels):
        raise ValueError(f"channels must be distinct, got {channels}")
    where = {c: i for i, c in enumerate(channels)}
    sensors = [Sensor(q, d, 1.0, f"unobserved {q} at DOF {d}") for q, d in channels]
    cols = []
    for s in model.sensors:
        i = where.get((s.quantity, s.dof))
        if i is None or i in cols:
            raise ValueError(f"channels {channels} have no channel of their own for the sensor {s}")
        cols.append(i)
        sensors[i] = s
    y, mask = np.asarray(y, dtype=float), np.asarray(mask, dtype=bool)
    if y.ndim != 2 or y.shape[1] != len(model.sensors) or mask.shape != y.shape:
        raise ValueError(
            f"y and mask must both be (T, {len(model.sensors)}), one column per sensor; got {y.shape} and {mask.shape}"
        )
    y_all = np.full((y.shape[0], len(channels)), np.nan)
    mask_all = np.zeros(y_all.shape, dtype=bool)
    y_all[:, cols], mask_all[:, cols] = y, mask
    return LatentForceModel(model.system, model.kernel, sensors), y_all, mask_all


def _unnamed(model):
    """``model`` with its sensors' names cleared: the programs' model, so that records whose channels
    are named otherwise (and the placeholders of :func:`observe_through`) share them. Inside, a name
    only keys a noise level in ``params``; the programs take the noise covariance as an argument."""
    from latentforce.models import LatentForceModel

    return LatentForceModel(model.system, model.kernel, [s._replace(name="") for s in model.sensors])
