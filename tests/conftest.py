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
import os
import shutil
import tempfile

import jax
import numpy as np
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


class LoweredPrograms:
    """The StableHLO text of compiled programs as a run calls them (fixture ``lowered_programs``)."""

    def __init__(self, monkeypatch):
        self.texts, self._seen, self._monkeypatch = [], set(), monkeypatch

    def record(self, *modules):
        """Replace every module-level compiled program (a ``jit`` function) of ``modules`` by one that
        also keeps its text, once per program and signature (the arguments' tree, the arrays' shapes
        and types, the other arguments' values: the optimiser calls one program hundreds of times)."""
        for module in modules:
            for name, prog in list(vars(module).items()):
                if not (callable(prog) and hasattr(prog, "lower") and hasattr(prog, "trace")):
                    continue

                def call(*args, _prog=prog, _name=name, **kw):
                    leaves, tree = jax.tree_util.tree_flatten((args, kw))
                    sig = tuple((np.shape(x), str(x.dtype)) if hasattr(x, "dtype") else x for x in leaves)
                    if (_name, tree, sig) not in self._seen:
                        self._seen.add((_name, tree, sig))
                        self.texts.append((_name, _prog.lower(*args, **kw).as_text()))
                    return _prog(*args, **kw)

                self._monkeypatch.setattr(module, name, call)

    @property
    def names(self):
        return {name for name, _ in self.texts}

    def lapack_calls(self):
        """The recorded programs whose text calls LAPACK."""
        return sorted({name for name, text in self.texts if "lapack" in text})


@pytest.fixture
def lowered_programs(monkeypatch):
    """Record the StableHLO text of the programs a test's run calls (:class:`LoweredPrograms`): used
    to check that the samplers' programs hold no LAPACK call (``latentforce.linalg`` says why) on
    runs the tests make anyway, not on runs of their own."""
    return LoweredPrograms(monkeypatch)


def pytest_runtest_logreport(report):
    """``LATENTFORCE_TEST_TIMES=file``: each test phase's seconds appended to ``file`` as it ends
    (tab-separated: node id, phase, seconds), so that a run's slow tests are known while it runs
    (``--durations`` prints only at the end, and not at all for a run stopped by a time limit)."""
    path = os.environ.get("LATENTFORCE_TEST_TIMES")
    if path and not os.environ.get("PYTEST_XDIST_WORKER"):  # the controller writes every worker's
        with open(path, "a", encoding="utf-8") as f:
            f.write(f"{report.nodeid}\t{report.when}\t{report.duration:.2f}\n")
