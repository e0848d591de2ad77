"""``latentforce.compile.jit``: jax.jit with our XLA CPU options, and its fallback."""

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


def test_options_are_used_exactly_when_this_jaxlib_accepts_them():
    if jax.default_backend() != "cpu":
        assert lc.cpu_options() == ()
        return
    try:
        jax.jit(_program, compiler_options=lc.CPU_OPTIONS)(jnp.zeros(3))
        accepted = True
    except Exception:
        accepted = False
    assert dict(lc.cpu_options()) == (lc.CPU_OPTIONS if accepted else {})


def test_an_unknown_option_falls_back_to_the_defaults(monkeypatch):
    monkeypatch.setattr(lc, "CPU_OPTIONS", {"xla_cpu_no_such_option_latentforce": True})
    lc.cpu_options.cache_clear()
    try:
        if jax.default_backend() == "cpu":
            with pytest.raises(Exception, match="no_such_option"):
                jax.jit(_program, compiler_options=lc.CPU_OPTIONS)(jnp.zeros(3))
        assert lc.cpu_options() == ()
        out = lc.jit(_program)(jnp.zeros(3))  # still compiles and runs
        assert np.all(np.isfinite(np.asarray(out[1])))
    finally:
        monkeypatch.undo()
        lc.cpu_options.cache_clear()
