"""The path moves' step counts per Gibbs block, the window move's width and the sweep's particle count
where :func:`~latentforce.inference.pgas.run_pgas` is given none.

How many smoother-move and residual-preserving steps a block makes depends on the model: its number of
DOFs, whether it is linear, and whether a channel reads the displacement. Each rule is a measurement,
given in its function's doc and in ``docs/nonlinear.md`` ("How many residual-preserving steps").
"""

from __future__ import annotations

from latentforce.inference import particle_model, window_move

#: sensor quantities that pin the displacement (:func:`default_residual_steps`)
DISPLACEMENT_CHANNELS = ("displacement", "strain")


def _displacement_measured(pm: particle_model.ParticleModel) -> bool:
    """Whether a channel reads displacement: by the model's channels, not the data, so that records run
    through the same channels (``run_pgas(channels=...)``) share one compiled block whichever they observe."""
    return any(s.quantity in DISPLACEMENT_CHANNELS for s in pm.model.sensors)


def default_smoother_steps(pm: particle_model.ParticleModel) -> int:
    """The smoother move's steps per block where the caller gives none: 8 on a nonlinear system with a
    displacement (or strain) channel, else 4 (one of each :data:`~latentforce.inference.smoother_move.CN_BETAS`).

    With a displacement channel the smoother move is what renews the path (it accepts ~90 % of its
    proposals on the Duffing, 25-30 % on the Bouc-Wen oscillator) and the residual-preserving move is
    off (:func:`default_residual_steps`), so it gets a larger share of the block. Measured, same
    records and seed, 8 against 4 steps (no residual-preserving steps in either): Duffing acc + disp
    converged in 19.5 / 20.1 / 23.3 / 24.9 s against 21 / 21 / 28 / 27 s (Matérn-1/2 ... 7/2); the
    Bouc-Wen oscillator at Matérn-3/2 converged in 140 s (R-hat 1.009, ESS 486) where 4 steps ended
    unconverged at the 180 s cap (1.011, 335); Matérn-1/2 95 s against 136 s, 5/2 R-hat 1.127 / ESS 21
    against 1.275 / 11 (docs/nonlinear.md). Without a displacement channel the
    move accepts a few per cent of its proposals (acceleration alone) and more steps would cost
    more than they buy; on a linear system its first step is already an exact draw.
    """
    return 8 if not pm.is_linear and _displacement_measured(pm) else 4


def default_residual_steps(pm: particle_model.ParticleModel, smoother_steps: int) -> int:
    """The residual-preserving move's steps per block where the caller gives none: 60 over the number of DOFs.

    60 on an SDOF system: on the acceleration-only Duffing, where the move's slow direction is the
    posterior's, 20 -> 60 steps raised the force's bulk ESS from 5-26 to 34-108 (docs/nonlinear.md).
    Fewer on more DOFs, whose steps cost more and, measured, buy less: on the 3-storey frame
    (acc0, acc2, T = 400, 240 s cap, one record per order) 20 steps instead of 60 reached
    the convergence rule 25-27 % sooner at every Matérn order with the same coverage
    (1/2: 226 s against unconverged at 257 s; 3/2: 142 against 189 s; 5/2: 153 against 209 s),
    and none at all 205 s on 1/2, so the move is not what the frame's mixing waits on.
    None on a linear system while the smoother move runs: that move is then an exact draw of
    the path given theta (acceptance 1), after which a move at fixed theta adds nothing; on the
    2-DOF linear suite (Matérn-3/2, acc and acc + disp) 0 steps converged in 26 and 30 s, 60 in 47
    and 37 s, both within the exact smoother's rule.
    None either where a channel measures displacement (or strain) while the smoother move runs: the
    move's direction, slow displacement content at fixed acceleration residuals, is then pinned by
    the data, and the smoother move (accepting ~90 % there) renews the path. Measured, same records
    and seed, 0 against 60 steps: Duffing acc + disp converged in 21 / 21 / 28 / 27 s against
    28 / 31 / 40 / 38 s (Matérn-1/2 ... 7/2, coverage unchanged); the Bouc-Wen oscillator (acc + disp,
    180 s cap) Matérn-1/2 converged in 136 s against 174 s, 3/2 R-hat 1.011 / ESS 335 against
    1.023 / 261, 5/2 1.275 / 11 against 2.03 / 5 (docs/nonlinear.md).
    """
    if int(smoother_steps) > 0 and (pm.is_linear or _displacement_measured(pm)):
        return 0
    return max(1, round(60 / pm.ndof))


#: the shortest record given the window move by default (:func:`default_window`)
WINDOW_MIN_T = 1024


def default_window(pm: particle_model.ParticleModel, T: int, smoother_steps: int) -> int:
    """The window move's width where the caller gives none: 256 samples on a nonlinear system with a
    displacement (or strain) channel, the smoother move on and at least :data:`WINDOW_MIN_T` samples
    (1 024); else 0, no window move.

    Where the whole-path smoother move's acceptance falls with the record (Duffing acc + disp,
    Matérn-3/2: 0.96 at T = 256, 0.66 at 1 024, 0.24 at 4 096) the window move renews the path a
    window at a time, the path on both sides held (:mod:`~latentforce.inference.window_move`).
    Measured at T = 4 096, 1 000 iterations after 500, 4 chains, one run each on one machine: without
    it 63 s, worst bulk ESS 11, R-hat 1.31; with it 97 s, ESS 431, R-hat 1.008 (25x the ESS per
    second; the first design, future innovations held with a tail of 1 024: 119 s, ESS 58); run
    "auto", converged in 137 s where both others stopped unconverged at the 600 s cap
    (docs/nonlinear.md, "Long records: the window move"). At Matérn-5/2 and 7/2 on that record (fixed
    counts): R-hat 1.011 / 1.021 with it, 3.5 / 4.1 without. Acceleration alone: off (the expansion is
    poor there, its weights' spread hundreds of nats; on the paper's Duffing, T = 1 024, Matérn-1/2, forced
    windows of 128 / 256 halved the time to converged with the hyperparameters fixed, 89 / 115 s against 206,
    but with them inferred as ``demo duffing`` runs it all three converged at the same check, 6 000
    iterations, in 247 / 252 s against 221; ``benchmarks/results/window_acc_only_paper.md``). The
    shortest record: measured after the correction became the whole transition into the held state (2026-12-02,
    ``benchmarks/results/window_min_t.md``, "auto", seconds to converged with / without): T = 1 024,
    Matérn-1/2 46 / 154, 3/2 43 / 41, 5/2 50 / 52 and 48 / 52, 7/2 65 / 182 and 69 / 169 (two
    records); T = 512, 5/2 40 / 29, 7/2 46 / 40. So on from 1 024 samples (it was 2 048 while a 7/2
    window accepted 0.78 and T = 1 024 measured 54 / 49 s at 3/2).
    """
    on = not pm.is_linear and int(smoother_steps) > 0 and _displacement_measured(pm) and T >= WINDOW_MIN_T
    return window_move.WIDTH if on else 0


#: the sweep's particles (:func:`default_particles`): the seed paper's count, and where the window move runs
PARTICLES = 50
WINDOW_PARTICLES = 16


def default_particles(window: int) -> int:
    """The conditional SMC sweep's particle count where the caller gives none: :data:`PARTICLES` (50),
    :data:`WINDOW_PARTICLES` (16) where the window move runs (``window`` > 0, :func:`default_window`).

    Where the window move runs, it renews the path (windows accepted 0.89-0.93 on the Duffing record
    below) and the sweep's ancestor switch rate is small (0.027 at Matérn-3/2, 0.0014 at 5/2), while
    the sweep over the whole record was most of the block's cost. Measured on the calibration Duffing
    (acc + disp, T = 4 096, 1 000 iterations after 500, 4 chains; one run each, one after another,
    2026-12-02; docs/nonlinear.md, "Long records: fewer particles"): Matérn-5/2 with 50 / 20 / 10
    particles 163 / 125 / 101 s, worst bulk ESS 447 / 479 / 396 (ESS a second 2.7 / 3.8 / 3.9), R-hat
    1.011-1.015 and force coverage 67.3 / 95.3 / 99.8 % at each; Matérn-3/2 with 50 / 10: 113 / 85 s,
    ESS 537 / 567. The sweep stays (it is the seed paper's kernel, and any particle count leaves the
    posterior invariant); 16 sits between the counts measured.
    """
    return WINDOW_PARTICLES if int(window) > 0 else PARTICLES
