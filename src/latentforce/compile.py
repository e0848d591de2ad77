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

**Programs shared within a process** (:func:`shared_jit`). A demo runs two
cases of one structure side by side (the same system, kernel, channels and
settings; other numbers), and on a first run compiling is most of its time:
about 30 s of processor time per case, two thirds of all of it. Two
``jax.jit`` functions built by two calls of a sampler are two functions to JAX,
so each case compiled every program anew. :func:`shared_jit` lowers as
``jax.jit`` does, then looks the lowered program's text up in a process-wide
table: a program that lowers to the same text (the same operations, shapes,
embedded constants and compiler options) gets the executable already
compiled, or waits for the thread compiling it. Keyed by the text, not by a
description of the inputs, and with what the executable holds outside the
text (the arguments JAX kept, devices, shardings; no sharing for programs
that call back into Python), a program is only shared with one that
computes the same thing. One thread at a time traces and lowers (Python
work, serialised by the interpreter lock anyway), so that one case traces
its next program while XLA compiles the other's, instead of both tracing
at half speed and then waiting on the same compile.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import hashlib
import os
import tempfile
import threading
from concurrent.futures import Future
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1,
               "xla_cpu_multi_thread_eigen": False, "xla_cpu_experimental_ynn_fusion_type": ""}


SMALL_LOOP_BYTES = 1_000_000
_EXTRA_OPTIONS_FLAG = "--xla_backend_extra_options"


def require_x64(what: str) -> None:
    """Refuse to run ``what`` unless JAX computes in float64 (:func:`latentforce.enable_x64`)."""
    if not jax.config.jax_enable_x64:
        from latentforce.errors import LatentForceError

        raise LatentForceError(
            f"{what} needs JAX's float64 mode, which is off: the Kalman recursions and lightly damped "
            "structural models lose too much precision in float32. Call latentforce.enable_x64() once at "
            "the start of your program (the latentforce command does), before any JAX computation.")


def raise_small_loop_threshold(environ=os.environ) -> bool:
    """Add ``xla_cpu_small_while_loop_byte_threshold`` (:data:`SMALL_LOOP_BYTES`) to ``XLA_FLAGS`` (module doc).

    Returns whether it did: not when JAX's backends are already initialised
    (the flag would be ignored), nor when ``XLA_FLAGS`` already sets backend
    extra options (the user's own; a second occurrence would replace them).
    """
    flags = environ.get("XLA_FLAGS", "")
    if _EXTRA_OPTIONS_FLAG in flags:
        return False
    try:
        from jax._src import xla_bridge

        if xla_bridge.backends_are_initialized():
            return False
    except (ImportError, AttributeError):  # a JAX without this check: setting the flag is harmless
        pass
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
    """``jax.jit(fn, **kwargs)`` with :func:`cpu_options`; usable as a decorator."""
    if fn is None:
        return functools.partial(jit, **kwargs)
    return jax.jit(fn, compiler_options=dict(cpu_options()), **kwargs)


# executables shared by text (module doc): key -> Future of a jax.stages.Compiled
_SHARED: collections.OrderedDict = collections.OrderedDict()
_SHARED_LOCK = threading.Lock()
SHARED_MAX = 64  # executables kept (the oldest are dropped)
# one thread at a time traces and lowers (module doc); reentrant, since a trace may
# call another program with concrete arguments
_LOWERING_LOCK = threading.RLock()


class SharedProgram:
    """``jax.jit(fn)`` with :func:`cpu_options` whose executables are shared by text (module doc).

    Called with concrete arguments it lowers once per argument signature and
    compiles through :func:`compile_shared`; called inside another trace it is
    the plain jitted function (inlined by the outer program, whose options apply).
    """

    def __init__(self, fn, **kwargs):
        self._options = dict(cpu_options())
        self._jitted = jit(fn, **kwargs)
        self._nested = jax.jit(fn, **kwargs)  # JAX takes compiler options only at the top level
        self._compiled: dict = {}
        functools.update_wrapper(self, fn)

    def __call__(self, *args, **kwargs):
        leaves, tree = jax.tree_util.tree_flatten((args, kwargs))
        if _tracing() or any(isinstance(x, jax.core.Tracer) for x in leaves):
            return self._nested(*args, **kwargs)
        # as jax.jit's own cache: the arguments' types and the settings that change a trace
        # (x64, default matmul precision, default device, ...)
        signature = (tree, tuple(_abstract(x) for x in leaves), _trace_context())
        compiled = self._compiled.get(signature)
        if compiled is None:
            with _LOWERING_LOCK:
                lowered = self._jitted.lower(*args, **kwargs)
            compiled = compile_shared(lowered, self._options)
            self._compiled[signature] = compiled
        return compiled(*args, **kwargs)

    def lower(self, *args, **kwargs):
        return self._jitted.lower(*args, **kwargs)


def _tracing() -> bool:
    """Whether this thread is inside a JAX trace (a call there must be inlined, even one
    whose arguments are all concrete: its function may close over a tracer)."""
    try:
        from jax._src import core

        return not core.trace_state_clean()
    except (ImportError, AttributeError):  # a JAX without it: the arguments tell
        return False


def _trace_context() -> tuple:
    try:
        from jax._src import config

        return config.trace_context()
    except (ImportError, AttributeError):
        return (jax.config.jax_enable_x64, str(jax.config.jax_default_matmul_precision),
                str(jax.config.jax_default_device))


def _abstract(x):
    """What a compiled program's input is checked against: shape, dtype and weak type."""
    typeof = getattr(jax, "typeof", None)  # JAX >= 0.4.36
    if typeof is not None:
        return typeof(x)
    return np.shape(x), str(getattr(x, "dtype", type(x))), bool(getattr(x, "weak_type", False))


def shared_jit(fn=None, **kwargs):
    """:class:`SharedProgram` of ``fn`` (``jax.jit`` keywords allowed); usable as a decorator."""
    if fn is None:
        return functools.partial(shared_jit, **kwargs)
    return SharedProgram(fn, **kwargs)


def compile_shared(lowered, options=None):
    """``lowered.compile()``, or the executable of a program with the same text (module doc).

    The key is the lowered module's text (operations, shapes, embedded
    constants), its argument and result trees, the compiler ``options`` and
    what the compiled program holds besides its text: which arguments it kept
    (JAX drops unused ones, so ``f(x, y) = 2x`` and ``g(x, y) = 2y`` lower to
    the same text), the backend, devices, shardings, layouts and effects.
    Nothing is shared (a plain compile) when that cannot be seen (a JAX
    without ``Lowered._lowering.compile_args``), when the program calls back
    into Python (the callback is not in the text), when JAX passes constants
    as arguments instead of embedding them (:func:`constants_are_embedded`),
    or when the text elides a constant.
    """
    compile_args = getattr(getattr(lowered, "_lowering", None), "compile_args", None)
    if not isinstance(compile_args, dict) or compile_args.get("host_callbacks") or not constants_are_embedded():
        return lowered.compile()
    text = lowered.as_text()
    if "__elided__" in text or "callback" in text:
        return lowered.compile()
    backend = compile_args.get("backend")
    outside = tuple(repr(compile_args.get(k)) for k in (
        "kept_var_idx", "num_devices", "in_shardings", "out_shardings", "in_layouts", "out_layouts",
        "ordered_effects", "unordered_effects", "tuple_args"))
    key = (hashlib.sha256(text.encode()).hexdigest(), str(lowered.in_tree), str(lowered.out_tree),
           repr(sorted((options or {}).items())), str(getattr(backend, "platform", backend))) + outside
    with _SHARED_LOCK:
        future = _SHARED.get(key)
        owner = future is None
        if owner:
            future = _SHARED[key] = Future()
            while len(_SHARED) > SHARED_MAX:
                _SHARED.popitem(last=False)
        else:
            _SHARED.move_to_end(key)
    if owner:
        try:
            future.set_result(lowered.compile())
        except BaseException as exc:  # the waiters see the error; a later call tries again
            future.set_exception(exc)
            with _SHARED_LOCK:
                if _SHARED.get(key) is future:
                    del _SHARED[key]
            raise
    return future.result()


def constants_are_embedded() -> bool:
    """Whether this JAX writes a program's closed-over arrays into its lowered text.

    Found out once per value of ``jax_use_simplified_jaxpr_constants``, from
    the text of a small program with two constants of 64 numbers (a NumPy and
    a JAX array): the sharing of :func:`compile_shared` is sound only if it does.
    """
    return _constants_are_embedded(getattr(jax.config, "jax_use_simplified_jaxpr_constants", None))


@functools.lru_cache(maxsize=4)
def _constants_are_embedded(_flag) -> bool:
    marker = np.full(64, 1234.5)
    marker[0] = 8765.25
    device_marker = jnp.asarray(-marker)
    text = jax.jit(lambda x: x + marker + 2.0 * device_marker).lower(np.zeros(64)).as_text()
    return all(v in text for v in ("8.765250e+03", "1.234500e+03", "-8.765250e+03", "-1.234500e+03"))


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

    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs",
             "jax_persistent_cache_min_entry_size_bytes", "jax_enable_compilation_cache")
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
