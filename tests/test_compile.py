"""``latentforce.compile.jit``: jax.jit with our XLA CPU options, and its fallback."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from latentforce import compile as lc


def _program(x):
    # a scan with a nonlinear step: the loop and fusion code the options change
    def step(c, u):
        c = c + 0.01 * jnp.sin(c) * u
        return c, jnp.exp(-c**2)

    return jax.lax.scan(step, x, jnp.linspace(0.0, 1.0, 200))


def test_jit_gives_the_default_build_result_to_round_off():
    x = jnp.linspace(-2.0, 2.0, 7)
    ours = jax.tree_util.tree_map(np.asarray, lc.jit(_program)(x))
    ref = jax.tree_util.tree_map(np.asarray, jax.jit(_program)(x))
    for a, b in zip(ours, ref):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


def _accepts(options):
    try:
        jax.jit(_program, compiler_options=options)(jnp.zeros(3))
        return True
    except Exception:
        return False


def test_options_are_used_exactly_when_this_jaxlib_accepts_them():
    if jax.default_backend() != "cpu":
        assert lc.cpu_options() == ()
        return
    expected = {k: v for k, v in lc.CPU_OPTIONS.items() if _accepts({k: v})}
    assert dict(lc.cpu_options()) == expected


def test_an_unknown_option_is_dropped_and_the_others_kept(monkeypatch):
    known = dict(list(lc.CPU_OPTIONS.items())[:1])
    monkeypatch.setattr(lc, "CPU_OPTIONS", {"xla_cpu_no_such_option_latentforce": True, **known})
    lc.cpu_options.cache_clear()
    try:
        if jax.default_backend() == "cpu":
            with pytest.raises(Exception, match="no_such_option"):
                jax.jit(_program, compiler_options={"xla_cpu_no_such_option_latentforce": True})(jnp.zeros(3))
            assert dict(lc.cpu_options()) == {k: v for k, v in known.items() if _accepts({k: v})}
        else:
            assert lc.cpu_options() == ()
        out = lc.jit(_program)(jnp.zeros(3))  # still compiles and runs
        assert np.all(np.isfinite(np.asarray(out[1])))
    finally:
        monkeypatch.undo()
        lc.cpu_options.cache_clear()


# ---------------------------------------------------------------------------
# XLA CPU's small-loop threshold (set in XLA_FLAGS by latentforce.enable_x64)
# ---------------------------------------------------------------------------
def test_threshold_is_added_to_xla_flags_unless_the_user_set_backend_options(monkeypatch):
    from jax._src import xla_bridge

    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: False)
    env = {}
    assert lc.raise_small_loop_threshold(env)
    assert env["XLA_FLAGS"] == (f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold="
                                f"{lc.SMALL_LOOP_BYTES}")
    env = {"XLA_FLAGS": "--xla_dump_to=/tmp/x"}
    assert lc.raise_small_loop_threshold(env)
    assert env["XLA_FLAGS"].startswith("--xla_dump_to=/tmp/x --xla_backend_extra_options=")
    mine = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=5"
    env = {"XLA_FLAGS": mine}
    assert not lc.raise_small_loop_threshold(env)  # the user's own backend options are kept
    assert env["XLA_FLAGS"] == mine
    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: True)
    env = {}
    assert not lc.raise_small_loop_threshold(env)  # too late: the backend read XLA_FLAGS already
    assert env == {}


_HOIST_PROBE = """
import sys
import jax
if sys.argv[1] == "plain":
    jax.devices()  # the backend starts before latentforce.enable_x64(): XLA_FLAGS is left alone
import latentforce
latentforce.enable_x64()
import jax.numpy as jnp
import numpy as np
from latentforce.inference import latent, path_moves, pgas, smc
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.systems import Duffing
T = 64
model = LatentForceModel(Duffing(), Matern(0), [Sensor("acceleration", 0, 0.1), Sensor("displacement", 0, 0.01)])
params = dict(m=1.0, c=0.2, k=10.0, k3=50.0, force_variance=1.0, force_lengthscale=0.5)
pm = smc.ParticleModel(model, params, 0.01, initial=(0.0, 0.01))
path = pm.path(jnp.zeros((T, pm.nl)))
y = jax.vmap(lambda x: pm._observe(x[:2], x[2:]))(path)
od = latent.observation_density(pm, y, jnp.ones(y.shape, bool))
rm = path_moves.ResidualMove(pm, T, 8, np.ones(pm.nm))
build = rm.builder(pm, od, path)
text = jax.jit(jax.vmap(lambda c: build(c)[1])).lower(jnp.zeros((2, rm.dim))).compile().as_text()
print("hoisted" if "xla_cpu_small_call" in text else "stepped")
"""


def test_the_threshold_makes_xla_run_batched_rebuild_loops_as_one_function(tmp_path):
    """In a fresh process, importing latentforce before JAX starts makes XLA compile the residual
    move's rebuild, batched over two chains, into one function (frontend attribute
    ``xla_cpu_small_call``); with the default threshold XLA steps it through its thunks."""
    import os
    import subprocess
    import sys

    if jax.default_backend() != "cpu":
        pytest.skip("a CPU-backend setting")
    script = tmp_path / "probe.py"
    script.write_text(_HOIST_PROBE)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["PYTHONPATH"] = os.pathsep.join([str(Path(lc.__file__).parents[1]), env.get("PYTHONPATH", "")])

    def probe(mode):
        out = subprocess.run([sys.executable, str(script), mode], capture_output=True, text=True, env=env,
                             timeout=300)
        assert out.returncode == 0, out.stderr
        return out.stdout.split()[-1]

    plain, ours = probe("plain"), probe("latentforce")
    if plain == "hoisted":
        pytest.skip("this jaxlib already runs the rebuild loop as one function")
    assert ours == "hoisted"


# ---------------------------------------------------------------------------
# Executables shared by text (shared_jit)
# ---------------------------------------------------------------------------
def _closure(constant):
    # a new function object each call, as a sampler builds its programs per run
    return lc.shared_jit(lambda x: _program(x * constant))


def _only_executable(program):
    (compiled,) = program._compiled.values()
    return compiled


def test_shared_jit_gives_jits_result_and_shares_executables_by_text():
    x = jnp.linspace(-1.0, 1.0, 5)
    c = np.arange(5.0)
    a, b, other = _closure(c), _closure(c.copy()), _closure(c + 1.0)
    ref = jax.jit(lambda x: _program(x * c))(x)
    for prog in (a, b):
        for got, want in zip(prog(x), ref):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-12, atol=1e-14)
    other(x)
    assert _only_executable(a) is _only_executable(b)  # same text: one executable
    assert _only_executable(other) is not _only_executable(a)  # another constant: another program
    # inside another trace it is the plain jitted function, inlined
    outer = jax.jit(lambda x: a(x)[1] * 2.0)(x)
    np.testing.assert_allclose(np.asarray(outer), 2.0 * np.asarray(ref[1]), rtol=1e-12)


def test_shared_jit_compiles_once_for_concurrent_callers():
    from concurrent.futures import ThreadPoolExecutor

    c = np.linspace(0.5, 1.5, 4) + 1e-3  # a constant no other test uses
    programs = [_closure(c) for _ in range(4)]
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda p: p(jnp.ones(4)), programs))
    assert len({id(_only_executable(p)) for p in programs}) == 1


class _Lowering:
    compile_args = {"kept_var_idx": {0}, "host_callbacks": []}


def test_a_failed_compile_is_not_kept():
    class Lowered:
        in_tree, out_tree = "in", "out"
        _lowering = _Lowering()
        calls = 0

        def as_text(self):
            return "module @a_failing_program_of_this_test"

        def compile(self):
            Lowered.calls += 1
            if Lowered.calls == 1:
                raise RuntimeError("out of memory")
            return "executable"

    with pytest.raises(RuntimeError, match="out of memory"):
        lc.compile_shared(Lowered())
    assert lc.compile_shared(Lowered()) == "executable"  # tried again, not the stored error
    assert lc.compile_shared(Lowered()) == "executable" and Lowered.calls == 2


def test_nothing_is_shared_when_constants_are_not_in_the_text(monkeypatch):
    monkeypatch.setattr(lc, "constants_are_embedded", lambda: False)
    c = np.arange(5.0) + 0.125
    a, b = _closure(c), _closure(c)
    a(jnp.ones(5)), b(jnp.ones(5))
    assert _only_executable(a) is not _only_executable(b)


def test_concurrent_compiles_of_one_text_wait_for_the_first():
    """Four threads lower the same program at once (a slow compile): one compiles, three wait."""
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    calls = []

    class Lowered:
        in_tree, out_tree = "in", "out"
        _lowering = _Lowering()

        def as_text(self):
            return "module @a_slow_program_of_this_test"

        def compile(self):
            calls.append(threading.get_ident())
            time.sleep(0.5)
            return object()

    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda _: lc.compile_shared(Lowered()), range(4)))
    assert len(calls) == 1 and all(g is got[0] for g in got)


def test_programs_with_the_same_text_but_other_arguments_or_callbacks_are_not_shared():
    """JAX drops unused arguments (f(x, y) = 2x and g(x, y) = 2y lower to one text), and a Python
    callback is not in the text: neither may share an executable."""
    x, y = jnp.ones(3), jnp.full(3, 5.0)
    first, second = lc.shared_jit(lambda x, y: x * 2.0), lc.shared_jit(lambda x, y: y * 2.0)
    np.testing.assert_array_equal(np.asarray(first(x, y)), 2.0)
    np.testing.assert_array_equal(np.asarray(second(x, y)), 10.0)

    def calling(offset):
        return lc.shared_jit(lambda v: jax.pure_callback(lambda a: np.asarray(a) + offset,
                                                         jax.ShapeDtypeStruct((3,), v.dtype), v))

    np.testing.assert_array_equal(np.asarray(calling(1.0)(x)), 2.0)
    np.testing.assert_array_equal(np.asarray(calling(100.0)(x)), 101.0)


def test_a_shared_program_closing_over_an_outer_tracer_is_inlined():
    out = jax.jit(lambda q: lc.shared_jit(lambda: q * 2.0)())(1.5)
    assert float(out) == 3.0


def test_persistent_cache_serves_a_new_process_and_restores_the_settings(tmp_path):
    """Every compile is written to the cache (no minimum compile time), a second process with
    other data of the same shape finds its program there, and the settings come back on exit."""
    import subprocess
    import sys

    before = jax.config.jax_compilation_cache_dir
    script = (
        "import sys, numpy as np, jax, jax.numpy as jnp\n"
        "from latentforce.compile import persistent_cache, jit\n"
        "from jax._src import monitoring\n"
        "hits = []\n"
        "monitoring.register_event_listener(lambda e, **k: hits.append(e) if 'cache_hits' in e else None)\n"
        "with persistent_cache(sys.argv[1]):\n"
        "    f = jit(lambda y: jnp.cumsum(jnp.sin(y)) @ y)\n"
        "    print(float(f(np.random.default_rng(int(sys.argv[2])).normal(size=64))))\n"
        "print('HITS', len(hits))\n")
    env = {**__import__("os").environ, "PYTHONPATH": str(Path(lc.__file__).resolve().parents[1])}
    runs = [subprocess.run([sys.executable, "-c", script, str(tmp_path), str(s)], capture_output=True, text=True,
                           env=env, timeout=300) for s in (1, 2)]
    for r in runs:
        assert r.returncode == 0, r.stderr
    assert any(tmp_path.iterdir())  # the first process wrote its program
    hits = [int(r.stdout.split("HITS")[1]) for r in runs]
    assert hits[0] == 0 and hits[1] >= 1, hits
    with lc.persistent_cache(tmp_path / "inner"):
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "inner")
    assert jax.config.jax_compilation_cache_dir == before


_IMPORT_PROBE = """
import json, os, sys
import jax
KEYS = ("jax_enable_x64", "jax_compilation_cache_dir", "jax_default_matmul_precision")
before = (dict(os.environ), {k: getattr(jax.config, k) for k in KEYS})
import latentforce, latentforce.cli, latentforce.estimate, latentforce.results, latentforce.inference.pgas
after = (dict(os.environ), {k: getattr(jax.config, k) for k in KEYS})
print(json.dumps(before == after))
if sys.argv[1] == "enable":
    latentforce.enable_x64()
    print("X64", jax.config.jax_enable_x64, "--xla_backend_extra_options" in os.environ.get("XLA_FLAGS", ""))
    sys.exit(0)
from latentforce.io.config import config_from_dict
try:
    config_from_dict({"system": {"type": "linear", "m": 1.0, "c": 0.1, "k": 1.0},
                      "force": {"kernel": "matern12", "variance": 1.0, "lengthscale": 1.0},
                      "sensors": [{"column": "a", "quantity": "acceleration", "noise_std": 0.1}]})
except latentforce.LatentForceError as exc:
    print("REFUSED", exc)
"""


def test_import_has_no_side_effects_and_float64_is_asked_for(tmp_path):
    """``import latentforce`` (and its main modules) leaves ``os.environ`` and JAX's settings alone;
    building a model without float64 is refused with a message; ``enable_x64`` sets both."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_ENABLE_X64")}
    env["PYTHONPATH"] = str(Path(lc.__file__).resolve().parents[1])
    outs = [subprocess.run([sys.executable, "-c", _IMPORT_PROBE, mode], capture_output=True, text=True, env=env,
                           timeout=300) for mode in ("refuse", "enable")]
    for out in outs:
        assert out.returncode == 0, out.stderr
    refuse, enable = (out.stdout.splitlines() for out in outs)
    assert refuse[0] == "true" and enable[0] == "true", (refuse, enable)
    assert refuse[1].startswith("REFUSED") and "latentforce.enable_x64()" in refuse[1], refuse
    assert enable[1] == "X64 True True", enable
