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
        return c, jnp.exp(-(c**2))

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
def test_threshold_is_added_to_xla_flags_unless_the_user_set_backend_options():
    env = {}
    assert lc.raise_small_loop_threshold(env)
    assert env["XLA_FLAGS"] == (
        f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold={lc.SMALL_LOOP_BYTES}"
    )
    env = {"XLA_FLAGS": "--xla_dump_to=/tmp/x"}
    assert lc.raise_small_loop_threshold(env)
    assert env["XLA_FLAGS"].startswith("--xla_dump_to=/tmp/x --xla_backend_extra_options=")
    mine = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=5"
    env = {"XLA_FLAGS": mine}
    assert not lc.raise_small_loop_threshold(env)  # the user's own backend options are kept
    assert env["XLA_FLAGS"] == mine


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
tr = pm.transition(1.0, 0.5)
build = rm.builder(pm, od, tr, path)
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
        out = subprocess.run([sys.executable, str(script), mode], capture_output=True, text=True, env=env, timeout=300)
        assert out.returncode == 0, out.stderr
        return out.stdout.split()[-1]

    plain, ours = probe("plain"), probe("latentforce")
    if plain == "hoisted":
        pytest.skip("this jaxlib already runs the rebuild loop as one function")
    assert ours == "hoisted"


# ---------------------------------------------------------------------------
# Numbers as arguments, structure static (Bound): JAX's own cache shares programs
# ---------------------------------------------------------------------------
def _scaled(static, numbers, x):
    (power,), (c,) = static, numbers
    return _program(x * c**power)


@lc.jit
def _apply(fn, x):
    return fn(x)


def _count_compiles(fn):
    seen = []

    def listen(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            seen.append(event)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        fn()
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    return len(seen)


def test_a_bound_function_shares_its_program_across_numbers_but_not_across_structure():
    x = jnp.linspace(-1.0, 1.0, 5)
    c, other = np.arange(5.0), np.arange(5.0) + 0.5
    ref = jax.jit(lambda x: _program(x * other))(x)
    _apply(lc.Bound(_scaled, (1,), (c,)), x)  # compiled here
    n = _count_compiles(lambda: _apply(lc.Bound(_scaled, (1,), (other,)), x))
    got = _apply(lc.Bound(_scaled, (1,), (other,)), x)
    assert n == 0  # other numbers: the same program, and its result is the other numbers'
    for g, w in zip(got, ref):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-12, atol=1e-14)
    assert _count_compiles(lambda: _apply(lc.Bound(_scaled, (2,), (c,)), x)) == 1  # another structure
    # a plain function through bound()/call(): its own program
    np.testing.assert_allclose(np.asarray(lc.call(lambda v: v * 3.0, x)), 3.0 * np.asarray(x))


def test_models_are_equal_by_structure_not_by_numbers():
    from latentforce.kernels import Matern
    from latentforce.models import LatentForceModel, Sensor
    from latentforce.systems import Duffing, LinearSystem

    def model(system, p, noise, quantity="acceleration"):
        return LatentForceModel(system, Matern(p), [Sensor(quantity, 0, noise, "acc")])

    a, b = model(Duffing(), 1, 0.1), model(Duffing(), 1, 0.3)
    assert a == b and hash(a) == hash(b)  # noise levels are numbers (model.noise_params)
    assert a.noise_params() == {"noise_std_acc": 0.1} and b.noise_params() == {"noise_std_acc": 0.3}
    assert a != model(Duffing(), 2, 0.1)  # kernel order
    assert a != model(LinearSystem(), 1, 0.1)  # system
    assert a != model(Duffing(), 1, 0.1, "velocity")  # sensor kind
    assert LinearSystem(2, (1,)) == LinearSystem(2, (1,)) != LinearSystem(2, (0,))


def test_jit_at_module_level_runs_no_jax_until_called(monkeypatch):
    calls = []
    monkeypatch.setattr(lc, "cpu_options", lambda: calls.append(1) or ())
    f = lc.jit(lambda x: x + 1.0)
    assert calls == []
    assert float(f(1.0)) == 2.0 and calls == [1]


def test_persistent_cache_serves_a_new_process_and_restores_the_settings(tmp_path):
    """Every compile is written to the cache (no minimum compile time), a second process with
    other data of the same shape finds its program there, and the settings come back on exit."""
    import subprocess
    import sys

    before = jax.config.jax_compilation_cache_dir
    script = (
        "import sys, numpy as np, jax, jax.numpy as jnp\n"
        "from latentforce.compile import persistent_cache, jit\n"
        "hits = []\n"
        "jax.monitoring.register_event_listener(lambda e, **k: hits.append(e) if 'cache_hits' in e else None)\n"
        "with persistent_cache(sys.argv[1]):\n"
        "    f = jit(lambda y: jnp.cumsum(jnp.sin(y)) @ y)\n"
        "    print(float(f(np.random.default_rng(int(sys.argv[2])).normal(size=64))))\n"
        "print('HITS', len(hits))\n"
    )
    env = {**__import__("os").environ, "PYTHONPATH": str(Path(lc.__file__).resolve().parents[1])}
    runs = [
        subprocess.run(
            [sys.executable, "-c", script, str(tmp_path), str(s)], capture_output=True, text=True, env=env, timeout=300
        )
        for s in (1, 2)
    ]
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
    outs = [
        subprocess.run(
            [sys.executable, "-c", _IMPORT_PROBE, mode], capture_output=True, text=True, env=env, timeout=300
        )
        for mode in ("refuse", "enable")
    ]
    for out in outs:
        assert out.returncode == 0, out.stderr
    refuse, enable = (out.stdout.splitlines() for out in outs)
    assert refuse[0] == "true" and enable[0] == "true", (refuse, enable)
    assert refuse[1].startswith("REFUSED") and "latentforce.enable_x64()" in refuse[1], refuse
    assert enable[1] == "X64 True True", enable
