"""The samplers' chunk loops as checkpoint contents, and back (:mod:`latentforce.checkpoint`).

A loop state is taken only at a chunk boundary, where everything a chain
needs to go on is in its state (parameters, path, adaptation, random key)
and the records of the chunks run so far; restoring it and running the
remaining chunks draws what the uninterrupted run draws, bit for bit.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.checkpoint import LoopState, tree_arrays, tree_from_arrays


def pgas_loop_state(
    states, infos: list, ref_q, done: int, finished: bool, stopped: str | None, elapsed_s: float, cut=None
) -> LoopState:
    """:func:`latentforce.inference.pgas.run_pgas`'s loop after its segment ending at block ``done``.

    ``states``: the chains' :class:`~latentforce.inference.pgas_block.ChainState`;
    ``infos``: the segments' :class:`~latentforce.inference.pgas_block.BlockInfo`
    records, chains first (merged into one here, in place, so that later
    checkpoints do not concatenate them again); ``ref_q``: the centring of
    the running sums; ``stopped``: why an ``"auto"`` run stopped, if it did; ``cut``: the block
    its warm-up stopped at (``max_time``; None: not cut).
    """
    infos[:] = [jax.tree_util.tree_map(lambda *a: np.concatenate(a, axis=1), *infos)]
    arrays = tree_arrays("state", states)
    arrays.update({f"info/{name}": np.asarray(v) for name, v in infos[0]._asdict().items()})
    arrays["ref_q"] = np.asarray(ref_q)
    return LoopState(done, finished, arrays, elapsed_s, {"stopped": stopped, "warm_up_cut": cut})


def pgas_restore(saved: LoopState, template, info_type) -> tuple:
    """``(states, infos, ref_q, done, finished, stopped, cut)`` from :func:`pgas_loop_state`'s record.

    ``template``: the run's freshly initialised chains (their tree and
    shapes); ``info_type``: the ``BlockInfo`` class. The centring ``ref_q``
    is the checkpoint's, not the resumed run's recomputation of it: the
    running sums in the states are centred on it.
    """
    states = tree_from_arrays(template, saved.arrays, "state")
    info = info_type(**{name: saved.arrays[f"info/{name}"] for name in info_type._fields})
    extra = saved.extra
    ref_q = jnp.asarray(saved.arrays["ref_q"])
    return (states, [info], ref_q, saved.done, saved.finished, extra.get("stopped"), extra.get("warm_up_cut"))
