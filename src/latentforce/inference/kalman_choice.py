r"""Which Kalman recursion runs: the sequential ``lax.scan`` or the parallel associative scan.

Both give the same numbers (tested to 1e-9, ``tests/test_parallel_kalman.py``);
they differ in cost. The sequential filter
(:mod:`latentforce.inference.kalman`) does :math:`O(T n^2)` work in :math:`T`
dependent steps; the parallel one
(:mod:`latentforce.inference.parallel_kalman`) does :math:`O(T n^3)` work in
:math:`O(\log T)` dependent steps. A CPU runs the few cheap steps fastest, so
there the sequential one always runs unless asked otherwise; a GPU runs a
long scan of tiny steps at one kernel launch per step, which is where the
parallel one is meant to win.

``[inference] kalman``: ``"auto"`` (the default) picks the parallel scan on a
GPU backend for records of at least :data:`PARALLEL_MIN_T` samples and the
sequential one otherwise; ``"sequential"`` and ``"parallel"`` force one. The
choice is made when a program is traced, from the record's static length.

Compile time is the parallel scan's other cost: ``lax.associative_scan``
traces its combination once per level of the scan (about ``2 log2 T``
copies) and XLA compiles each. Measured on the 2-core CPU development
machine under heavy load (JAX 0.10.2, 2026-11-26): the samplers' log
posterior at T = 1000 compiled in 135 s parallel against 10 s sequential,
with its forward-mode gradient in 309 s against 51 s
(``benchmarks/parallel_kalman.py``). The persistent compilation cache
(:mod:`latentforce.compile`) pays it once per record length.
"""

from __future__ import annotations

from collections.abc import Callable

import jax

from latentforce.inference import kalman, parallel_kalman

KALMAN_CHOICES = ("auto", "sequential", "parallel")
#: records at least this long use the parallel scan under "auto" on a GPU. Measured on an
#: H200 (benchmarks/results/parallel_kalman.md, JAX 0.11.2): at T = 1000 the parallel scan was
#: already 3.9x (log-likelihood), 5.1x (with gradient) and 26x (smoother) faster than the
#: sequential one there, and 28-170x at T = 10 000; shorter records were not measured, so the
#: threshold is the shortest measured length.
PARALLEL_MIN_T = 1000
_GPU_BACKENDS = ("gpu", "cuda", "rocm")


def use_parallel(choice: str, T: int, backend: str | None = None) -> bool:
    """Whether ``choice`` (``"auto" | "sequential" | "parallel"``) runs the parallel scan on ``T`` samples.

    ``backend`` defaults to ``jax.default_backend()``.
    """
    if choice == "sequential":
        return False
    if choice == "parallel":
        return True
    if choice != "auto":
        raise ValueError(f"kalman must be one of {KALMAN_CHOICES}, got {choice!r}")
    backend = jax.default_backend() if backend is None else backend
    return backend in _GPU_BACKENDS and T >= PARALLEL_MIN_T


def kalman_filter_for(choice: str, T: int) -> Callable:
    """The filter (``kalman_filter``'s signature and result) that ``choice`` picks for ``T`` samples."""
    return parallel_kalman.parallel_kalman_filter if use_parallel(choice, T) else kalman.kalman_filter


def rts_smoother_for(choice: str, T: int) -> Callable:
    """The smoother (``rts_smoother``'s signature and result) that ``choice`` picks for ``T`` samples."""
    return parallel_kalman.parallel_rts_smoother if use_parallel(choice, T) else kalman.rts_smoother


def log_likelihood_for(choice: str, T: int) -> Callable:
    """The log-likelihood (``log_likelihood``'s signature) that ``choice`` picks for ``T`` samples."""
    return parallel_kalman.parallel_log_likelihood if use_parallel(choice, T) else kalman.log_likelihood


def sample_smoothed_trajectory_for(choice: str, T: int) -> Callable:
    """The backward sampler (``sample_smoothed_trajectory``'s signature) that ``choice`` picks for ``T`` samples."""
    if use_parallel(choice, T):
        return parallel_kalman.parallel_sample_smoothed_trajectory
    return kalman.sample_smoothed_trajectory
