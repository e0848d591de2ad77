"""Test-session setup: the library computes in float64 (``latentforce.enable_x64``), which
importing it no longer switches on by itself; and each test module's compiled programs are
dropped when it ends.

Why the second: a pytest-xdist worker keeps every program it has compiled. On the 2-core,
24 GiB CI machine one worker had grown to 8.9 GB resident by the last third of the suite
(2026-11-27, 414 tests), and twice in a row a worker died of a segmentation fault inside XLA
(while compiling, and while tracing) in test_pgas.py's later tests: memory running out beside
the other worker and the demos' subprocesses. Programs are compiled per module anyway (the
compile-once tests count within a module), so clearing JAX's caches between modules costs
little.
"""

import gc

import jax
import pytest

import latentforce

latentforce.enable_x64()


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs_after_each_module():
    yield
    jax.clear_caches()
    gc.collect()
