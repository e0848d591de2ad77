"""Compiling our programs: :func:`jit` is ``jax.jit`` with XLA options chosen for the samplers.

The samplers are a few large programs of many tiny operations on small arrays
(a particle sweep is ~20 kernels per time step on arrays of 50 numbers), so on
a CPU their first run is dominated by XLA's compile time, not by arithmetic.
The first two XLA CPU options below change that (measured on the quick
Duffing demo's Gibbs block, one core); the third keeps Eigen off XLA's
thread pool; the fourth makes the sweep faster:

* ``xla_cpu_use_fusion_emitters = False``: the older loop emitters generate
  far less LLVM IR per fused kernel; compile time 27 s -> 22 s, run time equal;
* ``xla_backend_optimization_level = 1`` (default 2): LLVM's cheaper
  pipeline; a further 22 s -> 18 s, run time equal within the noise (the kernels
  are latency-bound, so the deeper loop optimisations buy nothing);
* ``xla_cpu_multi_thread_eigen = False``: Eigen's routines are not to use
  XLA's intra-op thread pool; our matrices are a few states across, so the
  pool buys nothing. It was added after a test run hung for good inside a
  Gibbs chunk, as a guess (others report a wedge of that pool), and it did
  not cure it: native stacks of a later hang showed the real cause, jaxlib's
  batched LAPACK calls blocking every pool thread, which
  :mod:`latentforce.linalg` now avoids (no LAPACK in our programs).
* ``xla_cpu_experimental_ynn_fusion_type = ""`` (no YNNPACK library
  fusions): XLA hands small dots to YNNPACK as "custom fusions", and in the
  particle sweep that is the inverse-CDF draw's cumulative sum (a product of
  2 x N weights with a constant N x N triangle) at every time step. XLA's own
  dot is faster at this size: one sweep (N = 50, T = 1024) 12.9 -> 9.0 ms for
  one chain, 10.9 -> 8.3 ms per chain with four vmapped (same process,
  interleaved). A custom fusion also keeps a loop from being run as one
  function (next paragraph).

The options are per program (``jax.jit(compiler_options=...)``), so they apply
to our programs only and only on the CPU backend. A jaxlib that no longer
knows an option rejects it with an error, not a crash: :func:`cpu_options`
finds out once per option, with a trivial program, and compiles without the
ones it rejects.
Compiled results differ from the default build only by round-off.

One more setting cannot be given per program, and it matters most for the
run time: **XLA CPU's small-loop threshold**. XLA runs a ``while`` loop either
as one compiled function (when its cost analysis counts fewer than
``xla_cpu_small_while_loop_byte_threshold`` bytes accessed, default 1024)
or step by step through its thunk executor, one call per operation per step.
Our path moves are scans of a thousand steps over a few numbers, and
batched over chains they pass the default threshold: the residual-preserving
move's rebuild, vmapped over two chains, ran 10x slower than one chain
(2 channels: 42 ms against 3.5 ms per 60 rebuilds), and the with-displacement
quick demo's Gibbs block took twice as long as the acceleration-only one
(110 ms against 63 ms; 50 ms each with the threshold raised). The threshold
is a backend option read once from ``XLA_FLAGS`` when JAX starts its CPU
backend, so :func:`raise_small_loop_threshold` (run by
:func:`latentforce.enable_x64`) adds it there, unless the backend is already running or the user's
``XLA_FLAGS`` set backend options of their own.

The value, 1 MB, is a compile-time trade. A loop holding a library call is
never merged, and since :mod:`latentforce.linalg` took LAPACK out of our
programs, large outer loops (the hyperparameter steps, each with its
transition and matrix exponential) became candidates too. At 10 MB they were
merged, and LLVM then compiled the quick demo's Gibbs chunk in 28 s instead
of 13-17 s, for a block about 10 % faster; at 1 MB the chunk compiles in
13 s, the path moves' loops are still merged, and a block costs what it did
(quick demo, 2 chains: about 58 ms either case on a busy machine).

**Numbers are arguments, structure is static.** A model is its structure
(sizes, kernel order, sensor kinds, nonlinearity: hashable, compared by
value) plus its numbers (a params dict of arrays). Every compiled program
is a module-level ``jit`` function that takes the numbers and the record as
arguments and the structure as a static argument, so JAX's own cache serves
every parameter value and every record of one shape: a campaign's second
record compiles nothing (``tests/test_compile_once.py``,
``benchmarks/compile_counts.py``). A function that needs numbers and
structure together travels into a program as a :class:`Bound`: a pytree whose
leaves are its numbers and whose static part (the function and the
structure) is in its tree definition.
"""

from __future__ import annotations

import contextlib
import functools
import os
import tempfile
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

CPU_OPTIONS = {
    "xla_cpu_use_fusion_emitters": False,
    "xla_backend_optimization_level": 1,
    "xla_cpu_multi_thread_eigen": False,
    "xla_cpu_experimental_ynn_fusion_type": "",
}


SMALL_LOOP_BYTES = 1_000_000
_EXTRA_OPTIONS_FLAG = "--xla_backend_extra_options"


def require_x64(what: str) -> None:
    """Refuse to run ``what`` unless JAX computes in float64 (:func:`latentforce.enable_x64`)."""
    if not jax.config.jax_enable_x64:
        from latentforce.errors import LatentForceError

        raise LatentForceError(
            f"{what} needs JAX's float64 mode, which is off: the Kalman recursions and lightly damped "
            "structural models lose too much precision in float32. Call latentforce.enable_x64() once at "
            "the start of your program (the latentforce command does), before any JAX computation."
        )


def raise_small_loop_threshold(environ=os.environ) -> bool:
    """Add ``xla_cpu_small_while_loop_byte_threshold`` (:data:`SMALL_LOOP_BYTES`) to ``XLA_FLAGS`` (module doc).

    Returns whether it did: not when ``XLA_FLAGS`` already sets backend extra
    options (the user's own; a second occurrence would replace them). XLA reads
    the flag when JAX starts its CPU backend, so it takes effect only if this
    runs before the first JAX computation (:func:`latentforce.enable_x64` says so;
    JAX has no public way to ask whether its backend has started).
    """
    flags = environ.get("XLA_FLAGS", "")
    if _EXTRA_OPTIONS_FLAG in flags:
        return False
    option = f"{_EXTRA_OPTIONS_FLAG}=xla_cpu_small_while_loop_byte_threshold={SMALL_LOOP_BYTES}"
    environ["XLA_FLAGS"] = f"{flags} {option}".strip()
    return True


@functools.lru_cache(maxsize=1)
def cpu_options() -> tuple:
    """The :data:`CPU_OPTIONS` this jaxlib accepts, as ``(name, value)`` pairs; empty off the CPU.

    Each option is tried on its own with a trivial program, so a jaxlib that
    lacks one of them still gets the others.
    """
    if jax.default_backend() != "cpu":
        return ()
    accepted = []
    for name, value in CPU_OPTIONS.items():
        try:
            jax.jit(lambda x: x + 1.0, compiler_options={name: value})(jnp.zeros(()))
        except Exception:  # an older or newer jaxlib without this option: its default
            continue
        accepted.append((name, value))
    return tuple(accepted)


def jit(fn=None, **kwargs):
    """``jax.jit(fn, **kwargs)`` with :func:`cpu_options`; usable as a decorator, also at module level:
    the options are found (which runs JAX) at the first call, not at import."""
    if fn is None:
        return functools.partial(jit, **kwargs)
    return _Jit(fn, kwargs)


class _Jit:
    """:func:`jit`'s function: ``jax.jit`` built at the first call or lowering.

    Called inside another program's trace it is the plain ``jax.jit`` (inlined there;
    JAX takes compiler options at the top level only, and says so with a ValueError).
    """

    def __init__(self, fn, kwargs):
        self._fn, self._kwargs, self._jitted, self._nested = fn, kwargs, None, None
        functools.update_wrapper(self, fn)

    def _get(self):
        if self._jitted is None:
            self._jitted = jax.jit(self._fn, compiler_options=dict(cpu_options()), **self._kwargs)
        return self._jitted

    def __call__(self, *args, **kwargs):
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((args, kwargs))):
            return self._plain()(*args, **kwargs)
        try:
            return self._get()(*args, **kwargs)
        except ValueError as exc:  # inside another trace with concrete arguments only
            if "compiler_options" not in str(exc) or not cpu_options():
                raise
            return self._plain()(*args, **kwargs)

    def _plain(self):
        if self._nested is None:
            self._nested = jax.jit(self._fn, **self._kwargs)
        return self._nested

    def lower(self, *args, **kwargs):
        return self._get().lower(*args, **kwargs)

    def trace(self, *args, **kwargs):
        return self._get().trace(*args, **kwargs)


@jax.tree_util.register_pytree_node_class
class Bound:
    """``fn(static, numbers, *args)`` as a callable pytree (module doc).

    ``numbers`` (any pytree of arrays) are its leaves, so a jitted function that
    takes a :class:`Bound` traces them as arguments; ``fn`` and ``static``
    (hashable, compared by value: a model's structure, names, settings) are its
    tree definition, so two :class:`Bound` of the same function and structure
    share compiled programs whatever their numbers. ``fn`` must be a
    module-level function (a fresh closure is a new key every time).
    """

    # No __weakref__ slot: JAX 0.11 jits a function only through a weak reference (jax.jit(bound)
    # raised "cannot create weak reference to 'Bound' object" on JAX 0.11.2, benchmarks/README.md),
    # but with the slot added under our JAX 0.10.2 a CI run's pytest worker crashed (segmentation
    # fault while tracing test_dispersed_start_fits_data_and_spreads_the_slow_directions), not yet
    # shown to be caused by it; the slot waits for the move to JAX 0.11.
    __slots__ = ("fn", "static", "numbers")

    def __init__(self, fn: Callable, static: Any, numbers: Any):
        self.fn, self.static, self.numbers = fn, static, numbers

    def __call__(self, *args, **kwargs):
        return self.fn(self.static, self.numbers, *args, **kwargs)

    def tree_flatten(self):
        return (self.numbers,), (self.fn, self.static)

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(aux[0], aux[1], children[0])

    def __repr__(self) -> str:
        return f"Bound({getattr(self.fn, '__name__', self.fn)!r}, {self.static!r})"


def _call_plain(fn, _numbers, *args, **kwargs):
    return fn(*args, **kwargs)


def bound(fn: Callable) -> Bound:
    """``fn`` as a :class:`Bound`: itself if it is one, else with no numbers of its own (a plain
    function or closure is then its own static key: a fresh closure compiles anew)."""
    return fn if isinstance(fn, Bound) else Bound(_call_plain, fn, ())


@jit
def _call(fn: Bound, *args):
    return fn(*args)


def call(fn: Callable, *args):
    """``fn(*args)`` as one compiled program (``fn`` a :class:`Bound`: one program per structure
    and argument shapes; a plain function: one per function)."""
    return _call(bound(fn), *args)


def numbers(params: dict) -> dict:
    """A params dict as the numbers of a compiled program: float64 NumPy arrays, so that a
    Python float, a NumPy scalar and an array of the same shape give one argument type."""
    return {k: np.asarray(v, dtype=float) for k, v in params.items()}


@contextlib.contextmanager
def persistent_cache(path: str | Path | None = None):
    """JAX's persistent compilation cache in ``path`` (a temporary directory when None), then as before.

    Every compile is cached, with no minimum compile time or size: a sampler
    compiles a few large programs and dozens of small ones (the Laplace
    start's, the mixture's), each a fraction of a second, and together they
    are most of a fresh process's time on a record of up to ~5e4 samples
    (``benchmarks/results/linear_long.md``; the calibration benchmark measured
    4.6 -> 1.3 s per replicate with every compile cached). The programs take
    the record as an argument, so a second record of the same shape and
    config reuses them. On exit the previous settings come back and the cache
    is reset, so later compiles in the process see the configuration they had.
    """
    from jax.experimental.compilation_cache import compilation_cache

    names = (
        "jax_compilation_cache_dir",
        "jax_persistent_cache_min_compile_time_secs",
        "jax_persistent_cache_min_entry_size_bytes",
        "jax_enable_compilation_cache",
    )
    old = {n: getattr(jax.config, n) for n in names}
    with contextlib.ExitStack() as stack:
        if path is None:
            path = stack.enter_context(tempfile.TemporaryDirectory(prefix="jax-cache-"))
        jax.config.update("jax_enable_compilation_cache", True)
        jax.config.update("jax_compilation_cache_dir", str(path))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
        # JAX decides once per process whether the cache is in use (at the first compile): ask again.
        compilation_cache.reset_cache()
        try:
            yield Path(path)
        finally:
            for n, v in old.items():
                jax.config.update(n, v)
            compilation_cache.reset_cache()
