"""Checkpoint and resume of ``estimate``: runs that survive being killed.

A sampler advances in *chunks* whose boundaries depend only on the
configuration (the Kalman samplers' chunks of ``n_chunk`` iterations, the
particle Gibbs sampler's segments of Gibbs blocks), and every random key of
a chunk is derived from the seed and the chunk's position (the Kalman
samplers fold the iteration count into each chain's key; a particle Gibbs
chain carries its key in its state). So the state of the chunk loop at a
boundary, :class:`LoopState`, is all a run needs to go on, and a run
continued from it draws exactly what the uninterrupted run would have
drawn: the final draws are bit-identical (on the same machine and the same
versions of latentforce, JAX and jaxlib).

The samplers see only a :class:`Checkpoint` (no files; STYLE 7): they offer
their loop state at every chunk boundary (:meth:`Checkpoint.save`, which
writes at most every ``checkpoint_every`` seconds) and ask for the saved
one when they start (:meth:`Checkpoint.restore`). A checkpoint is one
``checkpoint.npz`` in the result folder, written through a temporary file
in the same folder and :func:`os.replace`, so a kill at any moment leaves
either the previous checkpoint or the new one, never half of one. It holds
plain arrays and one JSON record (no pickles): the run's identity (the
config and data digests, the seed, the method, the versions), the loop's
position, whether the stopping rule already held, and the sampler time so
far.

What a resumed run counts as its time for ``max_time``: the sampler time
recorded in the checkpoint plus its own sampler time after the restore (the
time between the last checkpoint and the kill, and the start-up, are not
counted). A run that stops on ``max_time`` is therefore not bit-identical
to an uninterrupted one; runs that stop on their iteration count or on the
convergence verdict are.

Post-processing (the ``kalman-mcmc`` state mixture, the result files) is
not checkpointed: a resumed run recomputes it from the sampler's output.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time as _time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np

from latentforce.errors import LatentForceError

#: the checkpoint's file name in the result folder
CHECKPOINT_NAME = "checkpoint.npz"
#: layout version of the file (a reader refuses others)
FORMAT = 1
_TMP_PREFIX = ".checkpoint-"
_TMP_SUFFIX = ".npz.tmp"
_META = "__meta__"
#: Tests only: ``"N:written"`` stops the N-th write (1-based) of this process after the
#: temporary file is complete and before the rename; ``"N:renamed"`` after the rename.
#: The process then creates ``.test-stopped`` in the folder and sleeps until killed.
TEST_STOP_ENV = "LATENTFORCE_TEST_CHECKPOINT_STOP"
TEST_STOPPED_NAME = ".test-stopped"


@dataclass
class LoopState:
    """A sampler's chunk loop at a chunk boundary (what a checkpoint holds).

    ``done``: iterations (Kalman samplers) or Gibbs blocks (``pgas``) run;
    ``finished``: the stopping rule held after that chunk (only the
    post-processing is left); ``arrays``: named NumPy arrays (chain states,
    draws so far; :func:`tree_arrays`); ``elapsed_s``: the sampler's time so
    far (the ``max_time`` rule); ``extra``: small JSON-able facts.
    """

    done: int
    finished: bool
    arrays: dict[str, np.ndarray]
    elapsed_s: float = 0.0
    extra: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------
# Pytrees <-> named arrays
# ---------------------------------------------------------------------------
def _is_key(leaf) -> bool:
    return hasattr(leaf, "dtype") and jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)


def tree_arrays(prefix: str, tree) -> dict[str, np.ndarray]:
    """The leaves of ``tree`` as NumPy arrays named ``prefix`` + their path (typed
    random keys as their raw key data)."""
    out = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        out[prefix + jax.tree_util.keystr(path)] = np.asarray(jax.random.key_data(leaf) if _is_key(leaf) else leaf)
    return out


def tree_from_arrays(template, arrays: dict[str, np.ndarray], prefix: str):
    """``template``'s tree with its leaves replaced by ``arrays`` (:func:`tree_arrays`'s names).

    Every leaf must be there with the template's shape and dtype, else a
    :class:`LatentForceError` (a checkpoint written by another version or
    for another run). Random keys are rewrapped with the template's
    implementation.
    """
    leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
    new = []
    for path, leaf in leaves:
        name = prefix + jax.tree_util.keystr(path)
        want = jax.random.key_data(leaf) if _is_key(leaf) else leaf
        got = arrays.get(name)
        if got is None or got.shape != np.shape(want) or got.dtype != np.asarray(want).dtype:
            found = "missing" if got is None else f"{got.dtype}{list(got.shape)}"
            raise LatentForceError(
                f"The checkpoint does not fit this run: its array {name!r} is {found}, this run needs "
                f"{np.asarray(want).dtype}{list(np.shape(want))}. Was it written by another version of "
                "latentforce? Start the run again with --force."
            )
        arr = jax.numpy.asarray(got)
        new.append(jax.random.wrap_key_data(arr, impl=jax.random.key_impl(leaf)) if _is_key(leaf) else arr)
    return jax.tree_util.tree_unflatten(treedef, new)


# ---------------------------------------------------------------------------
# The run's identity
# ---------------------------------------------------------------------------
def config_content(config_path: Path) -> dict:
    """The configuration's content that decides the draws, comments and layout aside: the
    parsed TOML without ``[data].path`` (the data are identified by their own digest,
    wherever they lie) and ``[inference].checkpoint_every`` (it does not change the draws),
    as JSON values."""
    with open(config_path, "rb") as fh:
        raw = tomllib.load(fh)
    raw.get("data", {}).pop("path", None)
    raw.get("inference", {}).pop("checkpoint_every", None)
    return json.loads(json.dumps(raw, default=str))


def config_digest(config_path: Path) -> str:
    """SHA-256 of :func:`config_content` as canonical JSON."""
    text = json.dumps(config_content(config_path), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def run_identity(config_path: Path, data_path, seed: int, method: str) -> dict:
    """What a checkpoint must share with the run that resumes it (and the versions, recorded).

    ``data_path``: the data file, or every file the run reads (``[data].path`` first, then the
    sensors' own files): ``data`` is then the first and ``data_sha256`` covers them all."""
    import jaxlib

    from latentforce import __version__

    paths = [Path(data_path)] if isinstance(data_path, (str, Path)) else [Path(p) for p in data_path]
    digests = [file_digest(p) for p in paths]
    combined = digests[0] if len(digests) == 1 else hashlib.sha256("".join(digests).encode()).hexdigest()
    return {
        "config": str(Path(config_path).resolve()),
        "config_sha256": config_digest(config_path),
        "config_content": config_content(config_path),
        "data": str(paths[0].resolve()),
        "data_files": [str(p.resolve()) for p in paths],
        "data_sha256": combined,
        "seed": int(seed),
        "method": method,
        "version": __version__,
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
    }


# ---------------------------------------------------------------------------
# The checkpoint file
# ---------------------------------------------------------------------------
class Checkpoint:
    """The checkpoint of one run in ``out_dir`` (module doc).

    ``identity``: :func:`run_identity`; ``every``: the least number of
    seconds between two writes (0: at every chunk boundary); ``saved``: the
    loop state to resume from (:func:`read_checkpoint`), or None for a new
    run.
    """

    def __init__(
        self, out_dir: Path, identity: dict, every: float, saved: LoopState | None = None, sampler: str | None = None
    ):
        self.out_dir = Path(out_dir)
        self.path = self.out_dir / CHECKPOINT_NAME
        self.identity = dict(identity)
        self.every = float(every)
        self._saved = saved
        self._sampler = sampler
        self._last = _time.monotonic()
        self.writes = 0
        self.resumed_from: dict | None = None
        self.created_dir = False  # set by open_new
        remove_partial_writes(self.out_dir)

    def restore(self, sampler: str) -> LoopState | None:
        """The loop state to continue from, or None for a fresh start (once per run)."""
        saved, self._saved = self._saved, None
        if saved is None:
            return None
        if self._sampler is not None and self._sampler != sampler:
            raise LatentForceError(
                f"The checkpoint in {str(self.out_dir)!r} was written by the {self._sampler} "
                f"sampler, not {sampler}; start the run again with --force."
            )
        self.resumed_from = {
            "done": int(saved.done),
            "finished": bool(saved.finished),
            "sampler_time_before_s": float(saved.elapsed_s),
        }
        return saved

    def due(self) -> bool:
        """Whether :meth:`save` would write now."""
        return self.every <= 0 or _time.monotonic() - self._last >= self.every

    def save(self, sampler: str, build: Callable[[], LoopState], *, force: bool = False) -> bool:
        """Write ``build()`` if :meth:`due` (or ``force``); returns whether it wrote."""
        if not (force or self.due()):
            return False
        state = build()
        meta = {
            "format": FORMAT,
            "sampler": sampler,
            "identity": self.identity,
            "done": int(state.done),
            "finished": bool(state.finished),
            "elapsed_s": float(state.elapsed_s),
            "extra": state.extra,
            "written": _time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }
        if _META in state.arrays:
            raise ValueError(f"{_META} is reserved")
        arrays = dict(state.arrays)
        arrays[_META] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
        self.writes += 1
        try:
            fd, tmp = tempfile.mkstemp(dir=self.out_dir, prefix=_TMP_PREFIX, suffix=_TMP_SUFFIX)
            try:
                with os.fdopen(fd, "wb") as fh:
                    np.savez(fh, **arrays)
                    fh.flush()
                    os.fsync(fh.fileno())
                self._test_stop("written")
                os.replace(tmp, self.path)
            finally:
                if os.path.exists(tmp):
                    os.unlink(tmp)
            _fsync_dir(self.out_dir)
        except OSError as exc:
            raise LatentForceError(
                f"The checkpoint {str(self.path)!r} could not be written ({exc}); the run "
                "stopped. Free some space or set [inference].checkpoint_every."
            ) from None
        self._test_stop("renamed")
        self._last = _time.monotonic()
        return True

    def remove(self) -> None:
        """Delete the checkpoint (the run's results are written)."""
        if self.path.exists():
            self.path.unlink()
        remove_partial_writes(self.out_dir)

    def _test_stop(self, stage: str) -> None:
        spec = os.environ.get(TEST_STOP_ENV, "")
        if spec and spec == f"{self.writes}:{stage}":
            (self.out_dir / TEST_STOPPED_NAME).touch()
            while True:  # until the test kills us
                _time.sleep(60)


def _fsync_dir(path: Path) -> None:
    """Make the rename durable (POSIX; a no-op where folders cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def remove_partial_writes(out_dir: Path) -> None:
    """Delete the temporary files of checkpoint writes that were killed half-way."""
    if Path(out_dir).is_dir():
        for tmp in Path(out_dir).glob(f"{_TMP_PREFIX}*{_TMP_SUFFIX}"):
            tmp.unlink(missing_ok=True)


def read_checkpoint(out_dir: Path) -> tuple[dict, LoopState]:
    """``(meta, loop state)`` of the checkpoint in ``out_dir`` (it must exist)."""
    path = Path(out_dir) / CHECKPOINT_NAME
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
        meta = json.loads(arrays.pop(_META).tobytes().decode())
    except (OSError, ValueError, KeyError) as exc:
        raise LatentForceError(
            f"The checkpoint {str(path)!r} cannot be read ({exc}); start the run again with --force."
        ) from None
    if meta.get("format") != FORMAT:
        raise LatentForceError(
            f"The checkpoint {str(path)!r} has layout {meta.get('format')!r}; this version "
            f"of latentforce reads layout {FORMAT}. Start the run again with --force."
        )
    state = LoopState(
        int(meta["done"]), bool(meta["finished"]), arrays, float(meta["elapsed_s"]), dict(meta.get("extra") or {})
    )
    return meta, state


# ---------------------------------------------------------------------------
# The command's side: a new run, a resumed one
# ---------------------------------------------------------------------------
def open_new(out_dir: Path, identity: dict, every: float) -> Checkpoint:
    """The checkpoint of a new run in ``out_dir`` (already checked by
    :func:`latentforce.results.check_out_dir`): the folder is created now, so
    that the first checkpoint has a place; a stale checkpoint (of a run that
    ``--force`` replaces) is removed. ``created_dir`` says whether the folder
    is new (the command removes it again if the run fails before writing)."""
    out_dir = Path(out_dir)
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    checkpoint = Checkpoint(out_dir, identity, every)
    checkpoint.remove()
    checkpoint.created_dir = created
    return checkpoint


def open_resume(out_dir: Path) -> tuple[dict, LoopState]:
    """``(meta, loop state)`` of the interrupted run in ``out_dir``, or an error saying why
    there is nothing to resume (no folder, a finished run, no checkpoint)."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise LatentForceError(f"--resume {str(out_dir)!r}: there is no such result folder.")
    if not (out_dir / CHECKPOINT_NAME).is_file():
        if (out_dir / "summary.json").is_file():
            raise LatentForceError(
                f"--resume {str(out_dir)!r}: this run is finished (its results, summary.json and "
                "posterior.nc, are written and it holds no checkpoint); nothing to resume. To run it "
                "again, pass --out with --force instead."
            )
        raise LatentForceError(
            f"--resume {str(out_dir)!r}: the folder holds no checkpoint ({CHECKPOINT_NAME}), so there is "
            "nothing to resume: the run was stopped before its first checkpoint (one is written every "
            "[inference].checkpoint_every seconds), or the folder is not a result folder of "
            "`latentforce estimate`. Start the run again with --out and --force."
        )
    return read_checkpoint(out_dir)


def _flat(tree, prefix: str = "") -> dict:
    if isinstance(tree, dict):
        out = {}
        for k, v in tree.items():
            out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: tree}


def _config_changes(old: dict, new: dict) -> str:
    a, b = _flat(old), _flat(new)
    changes = []
    for key in sorted(set(a) | set(b)):
        if a.get(key, "<absent>") != b.get(key, "<absent>"):
            section, _, name = key.partition(".")
            where = f"[{section}].{name}" if name else f"[{section}]"
            changes.append(f"{where}: {a.get(key, '<absent>')!r} then, {b.get(key, '<absent>')!r} now")
    return "; ".join(changes[:6]) + (f"; and {len(changes) - 6} more" if len(changes) > 6 else "")


def check_same_run(meta: dict, identity: dict, out_dir: Path) -> None:
    """Refuse to resume the run in ``out_dir`` with another configuration, data, seed or
    version than its checkpoint's (``identity``: :func:`run_identity` of this command)."""
    saved = meta["identity"]
    where = f"The run in {str(out_dir)!r}"
    problems = []
    if saved["config_sha256"] != identity["config_sha256"]:
        changes = _config_changes(saved.get("config_content", {}), identity.get("config_content", {}))
        problems.append(
            f"the configuration {identity['config']!r} differs from the one the run was started "
            f"with ({saved['config']!r})" + (f": {changes}" if changes else "")
        )
    if saved["data_sha256"] != identity["data_sha256"]:
        problems.append(
            f"the data file {', '.join(map(repr, identity.get('data_files') or [identity['data']]))} differs "
            "from the one the run was started with "
            f"({saved['data']!r}; SHA-256 {saved['data_sha256'][:12]}... then, "
            f"{identity['data_sha256'][:12]}... now)"
        )
    if saved["seed"] != identity["seed"]:
        problems.append(
            f"the seed is {identity['seed']}, the run was started with seed {saved['seed']} "
            "(leave --seed out to keep it)"
        )
    if saved["version"] != identity["version"]:
        problems.append(f"the checkpoint was written by latentforce {saved['version']}, this is {identity['version']}")
    if problems:
        raise LatentForceError(
            f"{where} cannot be resumed: " + "; ".join(problems) + ". A resumed run must be the same run; "
            "nothing was changed. Resume with the original inputs, or start a new run with --force."
        )


def version_warning(meta: dict, identity: dict) -> str | None:
    """A warning when JAX or jaxlib changed since the checkpoint (the draws may then differ
    from the uninterrupted run's by round-off, though the run is as valid)."""
    saved = meta["identity"]
    changed = [f"{k} {saved.get(k)} -> {identity[k]}" for k in ("jax", "jaxlib") if saved.get(k) != identity[k]]
    if not changed:
        return None
    return (
        f"resumed with {', '.join(changed)}: the draws are valid but need not be bit-identical to an "
        "uninterrupted run's."
    )
