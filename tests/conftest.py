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

And every process of the session (the xdist controller's and each worker's) compiles through one
persistent compilation cache (:func:`latentforce.compile.persistent_cache`) in a temporary
directory made for the session and removed after it: a program that a test compiles again (in
a later module, after the caches above were dropped, or in the other worker) is read back
instead. The suite starts with an empty cache, so a run does not depend on an earlier one.
Measured on the 2-core machine (2026-11-28, 439 tests): 1 434 s with the shared cache against
1 516 s for the last CI run without it.
"""

import contextlib
import gc
import shutil
import tempfile

import jax
import pytest

import latentforce
from latentforce.compile import persistent_cache

latentforce.enable_x64()

_CACHE_KEY = "latentforce_xla_cache"
_session = contextlib.ExitStack()
_STASH = pytest.StashKey[str]()


def pytest_configure(config):
    workerinput = getattr(config, "workerinput", None)
    if workerinput is None:  # the controller (or a run without xdist) makes the directory
        path = tempfile.mkdtemp(prefix="latentforce-test-xla-")
        _session.callback(shutil.rmtree, path, ignore_errors=True)
        config.stash[_STASH] = path
    else:
        path = workerinput[_CACHE_KEY]
    _session.enter_context(persistent_cache(path))


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    """xdist: each worker gets the controller's cache directory."""
    node.workerinput[_CACHE_KEY] = node.config.stash[_STASH]


def pytest_unconfigure(config):
    _session.close()


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs_after_each_module():
    yield
    jax.clear_caches()
    gc.collect()
