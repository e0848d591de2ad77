"""How a PGAS run lays out its Gibbs blocks: the iteration bookkeeping (:class:`Schedule`) and the
segments of compiled scans between the burn-in's re-shapes (:func:`reshape_chunks`)."""

from __future__ import annotations

import math
from typing import NamedTuple

from latentforce.inference.hyper_moves import _RESHAPE_AT


class Schedule(NamedTuple):
    """Iteration bookkeeping of a Gibbs run (static integers; :func:`schedule`)."""

    state_every: int
    mh_steps: int
    burn_in: int  # iterations
    total: int  # iterations, burn-in included
    n_blocks: int  # Gibbs blocks, one sweep each
    burn_blocks: int  # blocks whose sweep is at an iteration < burn_in (they adapt)
    thin: int  # every thin-th post-burn-in path is stored
    n_draws: int  # stored paths


def schedule(burn_in: int, iterations: int, state_every: int = 1, mh_steps: int = 1, thin_draws: int = 200) -> Schedule:
    """The blocks of a run of ``burn_in + iterations`` iterations, a sweep on every ``state_every``-th."""
    k_every, n_mh = int(state_every), int(mh_steps)
    if n_mh < 1:
        raise ValueError(f"mh_steps must be at least 1, got {mh_steps}")
    if k_every < 1:
        raise ValueError(f"state_every must be at least 1, got {state_every}")
    total = int(burn_in) + int(iterations)
    n_blocks = -(-total // k_every)
    burn_blocks = -(-int(burn_in) // k_every)
    post_sweeps = n_blocks - burn_blocks
    thin = max(1, -(-post_sweeps // max(1, int(thin_draws))))
    n_draws = -(-post_sweeps // thin) if post_sweeps > 0 else 0
    return Schedule(k_every, n_mh, int(burn_in), total, n_blocks, burn_blocks, thin, n_draws)


def cut_warm_up(sched: Schedule, cut: int | None) -> Schedule:
    """``sched`` as run when its warm-up stopped after ``cut`` blocks (None: not cut; "auto" runs at half of
    ``max_time``, :func:`~latentforce.inference.pgas.run_pgas`): the burn-in ends there, and the compiled
    block, built for ``sched``, then numbers each later block ``sched.burn_blocks - cut`` higher, so that
    it adapts nothing more and records its draws from the first slot on."""
    if cut is None or cut >= sched.burn_blocks:
        return sched
    off = sched.burn_blocks - int(cut)
    return sched._replace(
        burn_in=int(cut) * sched.state_every,
        burn_blocks=int(cut),
        total=sched.total - off * sched.state_every,
        n_blocks=sched.n_blocks - off,
    )


#: the fewest draw sweeps before an "auto" run's first convergence check
FIRST_CHECK_SWEEPS = 20


def first_check(sched: Schedule, cut: int | None) -> int:
    """The block (in the compiled numbering of :func:`cut_warm_up`) from whose end on an "auto" run checks
    its convergence and ``max_time``: the verdict needs some draws, a tenth of the burn-in's sweeps and at
    least :data:`FIRST_CHECK_SWEEPS`; after a warm-up cut, when half of ``max_time`` is spent already,
    the floor alone, so that a run past ``max_time`` stops at its next segment's end."""
    after = (
        FIRST_CHECK_SWEEPS
        if cut is not None and cut < sched.burn_blocks
        else max(FIRST_CHECK_SWEEPS, sched.burn_blocks // 10)
    )
    return sched.burn_blocks + after


def reshape_chunks(
    n_blocks: int, burn_blocks: int, chunk_blocks: int, nonlinear: bool
) -> tuple[int, list[tuple[int, int]], tuple[int, ...]]:
    """``(scan_len, segments, reshape_at)``: how :func:`~latentforce.inference.pgas.run_pgas` runs its blocks.

    ``segments``: the ``(start, end)`` runs of blocks, each one call of one
    compiled program that scans ``scan_len >= end - start`` blocks and skips
    those at or past ``end``. ``reshape_at``: the blocks before which the path
    moves are re-shaped at each chain's path. For a linear model the
    Gauss-Newton shapes from the smoother are exact and nothing is re-shaped.
    For a nonlinear one the chain's path moves away from the smoother's, so the
    shapes are re-computed at fractions ``_RESHAPE_AT`` of the burn-in, by a
    program of their own shared with the start: inside the block (under a
    conditional) they added a quarter to its compile time. A scan of fixed
    length with skipped iterations, not one program per segment length: XLA
    unrolls short scans, and the block compiled twice as long at length 2.
    """
    chunk_blocks = max(1, int(chunk_blocks))
    scan_len = -(-n_blocks // max(1, -(-n_blocks // chunk_blocks)))
    at = (
        ()
        if not nonlinear
        else tuple(
            sorted({int(math.ceil(f * burn_blocks)) - 1 for f in _RESHAPE_AT if 1 <= math.ceil(f * burn_blocks) - 1})
        )
    )
    bounds = sorted(set(range(0, n_blocks, scan_len)) | {b for b in at if b < n_blocks} | {n_blocks})
    return scan_len, list(zip(bounds[:-1], bounds[1:])), at
