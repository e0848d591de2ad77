"""Speed of the PGAS kernel and of the blocked Gibbs sampler (Duffing, Matérn-1/2).

Prints one table: milliseconds per sweep for our JAX PGAS (1 chain; 4
vmapped chains, per chain-sweep), a plain NumPy implementation of the
sweep (written here, per-step vectorised over particles; it proposes the
force alone, without the within-step mechanical noise our latent carries,
so it does a little less work per step than the JAX sweep) and, if it can be
imported from its own virtual environment, the ``particles`` library's
conditional SMC (bootstrap, N=50); then ESS per second of the force at a few
time points and of the hyperparameters from a short Gibbs run. The four rows
are timed in rounds, each row once per round in turn (the peer in a
persistent worker process), and the peer's ratio to ours is taken within
each round, so that a change in the machine's load hits both sides of it.

    PYTHONPATH=src python benchmarks/pgas.py [--quick] [--particles-python /tmp/pvenv/bin/python]

``--quick`` (CI) uses few repetitions and a 150-iteration Gibbs run (about a minute on
an idle 2-core machine, most of it compilation). Both modes use T=1024, the paper's
record length and the size the issue's figures are for.
"""

from __future__ import annotations

import os

# One BLAS thread for the NumPy row and the peer (its worker inherits this). Their
# matrices are 3x3 to 50x50; idle BLAS threads spin after each call and take a core
# from the row timed next in the round (measured: our one-chain sweep 12.9 ms right
# after default-threaded NumPy rows, 10.1 ms with one thread; the peer alone is no
# faster with more threads, 610 against 564 ms median). Set to override.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import select
import subprocess
import sys
import tempfile
import textwrap
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import latentforce

latentforce.enable_x64()  # float64; XLA's small-loop threshold before JAX starts
from latentforce.compile import jit
from latentforce.inference import latent, pgas, smc
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.priors import LogNormal
from latentforce.systems import Duffing

PARAMS = dict(m=1.0, c=0.2, k=10.0, k3=50.0, force_variance=1.0, force_lengthscale=0.5)
NOISE = (0.01, 0.1)
DT = 0.01


def problem(T: int, seed: int = 0):
    model = LatentForceModel(
        Duffing(), Matern(0), [Sensor("displacement", 0, NOISE[0]), Sensor("acceleration", 0, NOISE[1])]
    )
    pm = smc.ParticleModel(model, PARAMS, DT, initial=(0.0, 0.01))
    tr = pm.transition(PARAMS["force_variance"], PARAMS["force_lengthscale"])
    path = pm.path(latent.gp_prior_path(jax.random.key(seed), tr, T))
    y = jax.vmap(lambda x: pm._observe(x[:2], x[2:]))(path)
    y = y + jax.random.normal(jax.random.key(seed + 1), y.shape) * jnp.asarray(NOISE)
    return model, pm, tr, np.asarray(y), np.asarray(path)


class ForceOnly(NamedTuple):
    """The force GP's scalar transition, for the NumPy and ``particles`` references."""

    A: np.ndarray
    Q: np.ndarray
    Pinf: np.ndarray


# ---------------------------------------------------------------------------
# JAX
# ---------------------------------------------------------------------------
def jax_sweeps(pm, tr, y, ref, N, chains, n_inner):
    """A compiled (and warmed-up) call running ``n_inner`` sweeps on each of ``chains`` vmapped chains."""
    mask = jnp.ones(y.shape, bool)
    sweep = smc.make_sweep(pm, N)

    def one(key, r):
        sc = smc.sweep_constants(pm, tr, jnp.asarray(y), mask)
        return sweep(key, sc, r).trajectory

    def many(key, r):  # n_inner sweeps in a scan: what the Gibbs loop does
        def body(r, k):
            return one(k, r), None

        r, _ = jax.lax.scan(body, r, jax.random.split(key, n_inner))
        return r

    f = jit(jax.vmap(many))
    keys = jax.random.split(jax.random.key(0, impl="rbg"), chains)
    refs = jnp.broadcast_to(jnp.asarray(ref), (chains,) + ref.shape)
    f(keys, refs).block_until_ready()
    return lambda: f(keys, refs).block_until_ready()


def timed(f):
    """``f`` as a call that returns its own wall time in seconds."""

    def call():
        t0 = time.perf_counter()
        f()
        return time.perf_counter() - t0

    return call


def interleaved_rounds(calls: dict, reps: int) -> dict:
    """Seconds per call in each of ``reps`` rounds, every round calling each entry once in turn,
    so that the entries of one round see the same machine load. An entry that returns
    ``None`` (a peer that stopped) is dropped from the later rounds."""
    times = {k: [] for k in calls}
    live = dict(calls)
    for _ in range(reps):
        for k, f in list(live.items()):
            t = f()
            if t is None:
                del live[k]
            else:
                times[k].append(t)
    return times


# ---------------------------------------------------------------------------
# NumPy reference: the same sweep (optimal proposal, AS with the information recursion)
# ---------------------------------------------------------------------------
class NumpySweep:
    def __init__(self, ft, y, N, rng):
        p = PARAMS
        self.m, self.c, self.k, self.k3 = p["m"], p["c"], p["k"], p["k3"]
        self.A, self.Q = float(ft.A[0, 0]), float(ft.Q[0, 0])
        self.Pinf = float(ft.Pinf[0, 0])
        self.y, self.N, self.rng = y, N, rng
        self.R = np.diag(np.square(NOISE))
        self.Rinv = np.linalg.inv(self.R)
        self.D = np.array([0.0, 1.0 / self.m])

    def acc(self, z, v, u):
        return (u - self.c * v - self.k * z - self.k3 * z**3) / self.m

    def phi(self, z, v, u):
        h = DT
        k1z, k1v = v, self.acc(z, v, u)
        k2z, k2v = v + 0.5 * h * k1v, self.acc(z + 0.5 * h * k1z, v + 0.5 * h * k1v, u)
        k3z, k3v = v + 0.5 * h * k2v, self.acc(z + 0.5 * h * k2z, v + 0.5 * h * k2v, u)
        k4z, k4v = v + h * k3v, self.acc(z + h * k3z, v + h * k3v, u)
        return z + h / 6 * (k1z + 2 * k2z + 2 * k3z + k4z), v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)

    def offset(self, z, v):
        return np.stack([z, -(self.c * v + self.k * z + self.k3 * z**3) / self.m], axis=-1)

    def __call__(self, ref):
        T, N, rng, D, R = len(self.y), self.N, self.rng, self.D, self.R
        # information recursion along the reference (Jacobians by central differences)
        Lam = np.zeros((T, 2, 2))
        eta = np.zeros((T, 2))
        eps = 1e-6
        for t in range(T - 1, -1, -1):
            z, v, u = ref[t]
            C = np.stack(
                [
                    (self.offset(z + eps, v) - self.offset(z - eps, v)) / (2 * eps),
                    (self.offset(z, v + eps) - self.offset(z, v - eps)) / (2 * eps),
                ],
                axis=1,
            )
            e = self.y[t] - self.offset(z, v) - D * u
            Lam[t] = C.T @ self.Rinv @ C
            eta[t] = C.T @ self.Rinv @ e
            if t < T - 1:
                J = np.stack(
                    [
                        np.array(self.phi(z + eps, v, u)) - np.array(self.phi(z - eps, v, u)),
                        np.array(self.phi(z, v + eps, u)) - np.array(self.phi(z, v - eps, u)),
                    ],
                    axis=1,
                ) / (2 * eps)
                Lam[t] += J.T @ Lam[t + 1] @ J
                eta[t] += J.T @ eta[t + 1]
        S = self.Q * np.outer(D, D) + R
        Sinv = np.linalg.inv(S)
        K = self.Q * D @ Sinv
        sig = np.sqrt(self.Q - K @ S @ K)
        X = np.zeros((T, N, 3))
        anc = np.zeros((T, N), int)
        z = rng.normal(0, 0.01, N)
        v = rng.normal(0, 0.01, N)
        z[-1], v[-1] = ref[0, 0], ref[0, 1]
        S0 = self.Pinf * np.outer(D, D) + R
        K0 = self.Pinf * D @ np.linalg.inv(S0)
        r = self.y[0] - self.offset(z, v)
        u = r @ K0 + np.sqrt(self.Pinf - K0 @ S0 @ K0) * rng.normal(size=N)
        u[-1] = ref[0, 2]
        logw = -0.5 * np.einsum("nd,de,ne->n", r, np.linalg.inv(S0), r)
        logw -= np.logaddexp.reduce(logw)
        X[0] = np.stack([z, v, u], 1)
        for t in range(1, T):
            zp, vp = self.phi(X[t - 1, :, 0], X[t - 1, :, 1], X[t - 1, :, 2])
            m = self.A * X[t - 1, :, 2]
            r = self.y[t] - self.offset(zp, vp) - np.outer(m, D)
            lw = logw - 0.5 * np.einsum("nd,de,ne->n", r, Sinv, r)
            w = np.exp(lw - lw.max())
            a = np.searchsorted(np.cumsum(w), rng.uniform(size=N) * w.sum())
            delta = np.stack([zp - ref[t, 0], vp - ref[t, 1]], 1)
            as_lw = (
                logw
                - 0.5 * (ref[t, 2] - m) ** 2 / self.Q
                - 0.5 * np.einsum("ni,ij,nj->n", delta, Lam[t], delta)
                + delta @ eta[t]
            )
            wa = np.exp(as_lw - as_lw.max())
            a[-1] = np.searchsorted(np.cumsum(wa), rng.uniform() * wa.sum())
            a = np.minimum(a, N - 1)
            u = m[a] + r[a] @ K + sig * rng.normal(size=N)
            u[-1] = ref[t, 2]
            X[t] = np.stack([zp[a], vp[a], u], 1)
            anc[t] = a
            logw = np.full(N, -np.log(N))
        k = rng.integers(N)
        path = np.empty((T, 3))
        for t in range(T - 1, -1, -1):
            path[t] = X[t, k]
            k = anc[t, k]
        return path


# ---------------------------------------------------------------------------
# particles (Chopin), in its own venv
# ---------------------------------------------------------------------------
PARTICLES_SCRIPT = textwrap.dedent("""
    import sys, time, numpy as np
    import particles
    from particles import mcmc, state_space_models as ssms, distributions as dists
    y = np.load(sys.argv[1]); T = len(y); N = int(sys.argv[2])
    A, Q, Pinf = float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
    m, c, k, k3, dt = 1.0, 0.2, 10.0, 50.0, %(dt)r
    R = np.diag(np.square(%(noise)r))
    def acc(z, v, u): return (u - c*v - k*z - k3*z**3) / m
    def phi(x):
        z, v, u = x[:, 0], x[:, 1], x[:, 2]; h = dt
        k1z, k1v = v, acc(z, v, u)
        k2z, k2v = v + .5*h*k1v, acc(z + .5*h*k1z, v + .5*h*k1v, u)
        k3z, k3v = v + .5*h*k2v, acc(z + .5*h*k2z, v + .5*h*k2v, u)
        k4z, k4v = v + h*k3v, acc(z + h*k3z, v + h*k3v, u)
        return np.stack([z + h/6*(k1z+2*k2z+2*k3z+k4z), v + h/6*(k1v+2*k2v+2*k3v+k4v), A*u], 1)
    class LFM(ssms.StateSpaceModel):
        def PX0(self):
            return dists.MvNormal(loc=np.zeros(3), cov=np.diag([1e-4, 1e-4, Pinf]))
        def PX(self, t, xp):
            # the mechanical states are deterministic: a tiny variance stands in (bootstrap only)
            return dists.MvNormal(loc=phi(xp), cov=np.diag([1e-12, 1e-12, Q]))
        def PY(self, t, xp, x):
            z, v, u = x[:, 0], x[:, 1], x[:, 2]
            return dists.MvNormal(loc=np.stack([z, acc(z, v, u)], 1), cov=R)
    ssm = LFM()
    fk = ssms.Bootstrap(ssm=ssm, data=list(y))
    pf = particles.SMC(fk=fk, N=N, resampling="multinomial", ESSrmin=1.0, store_history=True)
    pf.run()
    x = pf.hist.extract_one_trajectory()
    print("ready", flush=True)
    for line in sys.stdin:  # one conditional SMC sweep per request, its time in ms
        t0 = time.perf_counter()
        cpf = mcmc.CSMC(fk=fk, N=N, ESSrmin=1.0, xstar=x)
        cpf.run()
        x = cpf.hist.extract_one_trajectory()
        print(1e3 * (time.perf_counter() - t0), flush=True)
""")


class ParticlesPeer:
    """The ``particles`` library's conditional SMC in its own interpreter, one sweep per request.

    A persistent worker, so that its sweeps can be timed in the same rounds as ours
    (:func:`interleaved_rounds`): the ratio then compares runs under the same load.
    ``sweep()`` returns the worker's own timing of one sweep in seconds, or ``None``
    (with ``why`` set) once the worker has failed.
    """

    TIMEOUT = 600.0

    def __init__(self, python, y, ft, N):
        self.proc, self.why = None, ""
        if not python or not os.path.exists(python):
            self.why = f"no interpreter at {python!r}"
            return
        self._dir = tempfile.TemporaryDirectory()
        d = self._dir.name
        script = os.path.join(d, "p.py")
        with open(script, "w") as fh:
            fh.write(PARTICLES_SCRIPT % {"dt": DT, "noise": NOISE})
        np.save(os.path.join(d, "y.npy"), y)
        cmd = [
            python,
            script,
            os.path.join(d, "y.npy"),
            str(N),
            repr(float(ft.A[0, 0])),
            repr(float(ft.Q[0, 0])),
            repr(float(ft.Pinf[0, 0])),
        ]
        self._err = open(os.path.join(d, "stderr.txt"), "w+")
        self.proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._err, text=True, bufsize=1
        )
        if self._read() != "ready":
            self._fail()

    def _read(self):
        ready, _, _ = select.select([self.proc.stdout], [], [], self.TIMEOUT)
        return self.proc.stdout.readline().strip() if ready else None

    def _fail(self, why=None):
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self._err.seek(0)
            lines = self._err.read().strip().splitlines()
            self.why = why or (lines[-1] if lines else f"exit {self.proc.returncode}")
            self.proc = None

    def sweep(self):
        if self.proc is None:
            return None
        try:
            self.proc.stdin.write("sweep\n")
            self.proc.stdin.flush()
            line = self._read()
            return float(line) / 1e3
        except (OSError, TypeError, ValueError):
            self._fail(None if self.proc.poll() is not None else "no answer in 600 s")
            return None

    def close(self):
        if self.proc is not None:
            self.proc.stdin.close()
            self.proc.wait(timeout=60)
            self.proc = None
        if hasattr(self, "_dir"):
            self._err.close()
            self._dir.cleanup()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--particles-python", default="/tmp/pvenv/bin/python")
    ap.add_argument("--T", type=int, default=None)
    ap.add_argument(
        "--out", default=None, help="Markdown table (default benchmarks/results/pgas.md; none with --quick)"
    )
    args = ap.parse_args(argv)
    T = args.T or 1024
    N = 50
    reps = 3 if args.quick else 9
    n_inner = 10 if args.quick else 50
    model, pm, tr, y, truth = problem(T)
    ref = np.asarray(pm.path(jnp.zeros((T, pm.nl))))
    ft = ForceOnly(*pm.force_transition(PARAMS["force_variance"], PARAMS["force_lengthscale"]))
    print(f"Duffing, Matern-1/2, T={T}, N={N}, backend={jax.default_backend()}, cpus={os.cpu_count()}")

    one = jax_sweeps(pm, tr, y, ref, N, 1, n_inner)
    four = jax_sweeps(pm, tr, y, ref, N, 4, n_inner)
    nps = NumpySweep(ft, y, N, np.random.default_rng(0))
    nps(ref)
    peer = ParticlesPeer(args.particles_python, y, ft, N)
    try:
        peer.sweep()  # its first sweep warms up, as ours did
        # seconds per sweep (per chain-sweep for four chains), each entry once per round
        calls = {
            "one": lambda: timed(one)() / n_inner,
            "four": lambda: timed(four)() / (4 * n_inner),
            "numpy": timed(lambda: nps(ref)),
            "peer": peer.sweep,
        }
        sec = interleaved_rounds(calls, reps)
    finally:
        peer.close()
    ms = {k: 1e3 * float(np.median(v)) if v else None for k, v in sec.items()}
    ms1, ms4 = ms["one"], ms["four"]
    rows = [
        ("JAX PGAS, 1 chain", ms1, ""),
        ("JAX PGAS, 4 vmapped chains (per chain-sweep)", ms4, ""),
        ("NumPy PGAS (same sweep)", ms["numpy"], ""),
        ("particles CSMC", ms["peer"], "bootstrap CSMC, no AS" if ms["peer"] is not None else peer.why),
    ]
    table = ["| implementation | ms/sweep | × JAX 1 chain | note |", "|---|---:|---:|---|"]
    print(f"{'implementation':48s} {'ms/sweep':>10s} {'x JAX-1':>8s}  note")
    for name, t, note in rows:
        if t is None:
            print(f"{name:48s} {'unavailable':>10s} {'':>8s}  {note}")
            table.append(f"| {name} | unavailable | | {note} |")
        else:
            print(f"{name:48s} {t:10.2f} {t / ms1:8.2f}  {note}")
            table.append(f"| {name} | {t:.2f} | {t / ms1:.2f} | {note} |")
    budget = 2e4 * ms4 / 1e3
    print(f"-> 2e4 sweeps at this cost (4 chains vmapped, per chain): {budget:.0f} s")
    n_peer = len(sec["peer"])
    if n_peer:
        # the ratio within each round (same load), then its median and range over the rounds
        r1 = np.array(sec["peer"]) / np.array(sec["one"][:n_peer])
        r4 = np.array(sec["peer"]) / np.array(sec["four"][:n_peer])
        peer_line = (
            f"particles CSMC / JAX, per round of {n_peer}: one chain median {np.median(r1):.1f}x "
            f"(range {r1.min():.1f}-{r1.max():.1f}), a chain-sweep of 4 vmapped chains median "
            f"{np.median(r4):.1f}x (range {r4.min():.1f}-{r4.max():.1f}); aim: 50x, "
            f"{'met' if np.median(r1) >= 50 else 'not met'} one chain"
        )
    else:
        peer_line = f"particles CSMC: unavailable ({peer.why})"
    print(f"-> {peer_line}")
    if not args.quick or args.out:
        out = args.out or os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "pgas.md")
        load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
        with open(out, "w") as fh:
            fh.write(
                f"# PGAS sweep benchmark\n\nDuffing, Matérn-1/2 force, displacement + acceleration sensors; "
                f"T = {T}, N = {N} particles, optimal proposal, ancestor sampling.\n"
                f"{time.strftime('%Y-%m-%dT%H:%M:%S')}; {os.cpu_count()} cores, load average {load}; "
                f"JAX {jax.__version__} on {jax.default_backend()}; NumPy {np.__version__}. Medians of "
                f"{reps} rounds; a round times each row once in turn (JAX rows: {n_inner} sweeps, sweep "
                "constants included, as in the Gibbs loop; the peer: one sweep, timed in its own "
                "interpreter).\n\n"
            )
            fh.write("\n".join(table) + "\n\n")
            fh.write(f"2e4 sweeps at the 4-chain per-chain cost: {budget:.0f} s.\n\n{peer_line}.\n")
        print(f"wrote {out}")

    # ---- ESS/s from a short Gibbs run
    iters = 100 if args.quick else 2000
    free = {"force_variance": (LogNormal(0.0, 1.0), 2.0), "force_lengthscale": (LogNormal(-0.5, 1.0), 1.0)}
    t0 = time.perf_counter()
    out = pgas.run_pgas(
        jax.random.key(1, impl="rbg"),
        model,
        PARAMS,
        free,
        y,
        np.isfinite(y),
        DT,
        particles=N,
        iterations=iters,
        burn_in=iters // 2,
        state_every=1,
        chains=4,
        initial=(0.0, 0.01),
    )
    wall = time.perf_counter() - t0
    d = out.diagnostics
    print(
        f"Gibbs: 4 chains x {iters + iters // 2} iterations in {wall:.1f} s (incl. compile); "
        f"switch rate {np.mean(d['switch_rate']):.2f}, MH acceptance {np.mean(d['acceptance']):.2f}, "
        f"ESS/N {np.mean(d['ess_per_particle']):.2f}"
    )
    print(f"{'quantity':24s} {'R-hat':>7s} {'ESS':>8s} {'ESS/s':>8s}")
    for name, rh in d["rhat"].items():
        ess = d["ess_bulk"][name]
        print(f"{name:24s} {rh:7.3f} {ess:8.0f} {ess / wall:8.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
