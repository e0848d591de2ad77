"""The particle-Gibbs chain's state and each Gibbs block's record (pytrees, vmapped over chains).

Split from :mod:`latentforce.inference.pgas_block`, which builds the block that carries a
:class:`ChainState` from one block to the next and reports a :class:`BlockInfo` per block;
:class:`BlockData` is the record and what is precomputed from it, the compiled programs' arguments.
"""

from __future__ import annotations

from typing import NamedTuple

from jaxtyping import Array, Float

from latentforce.inference import mcmc, particle_model
from latentforce.inference.latent import ObservationDensity


class ChainState(NamedTuple):
    """State of one chain between Gibbs blocks (a pytree; vmapped over chains)."""

    key: Array
    reference: Float[Array, "T n"]
    rwm: mcmc.RWMState  # hyperparameters x = log(theta) and their centred random walk's adaptation
    rwm_nc: mcmc.RWMState  # the non-centred (interweaving) random walk's adaptation; its x mirrors rwm.x
    rwm_lf: mcmc.RWMState  # the low-frequency trajectory move's adaptation (x: its last coordinates)
    rwm_rp: mcmc.RWMState  # the residual-preserving move's adaptation
    # the latent's transition at rwm.x, carried so that a compiled block evaluates the
    # transition at only two places (its matrix exponentials were 40 % of the program)
    tr: particle_model.Transition
    block: Array  # Gibbs block counter
    # running sums over post-burn-in state samples: (z, v, u) per time
    sum1: Float[Array, "T q"]
    sum2: Float[Array, "T q"]
    count: Float[Array, ""]
    draws: Float[Array, "S T n"]  # thinned trajectories (last slot is a discard slot)
    thin: Array  # every thin-th post-burn-in sweep is stored (doubled by run_pgas as "auto" runs on)
    # every channel's noise variance (SI): the inferred ones drawn (noise_gibbs), the others as
    # configured; None where no noise level is inferred (then the block uses BlockData.R)
    noise_var: Float[Array, " d"] | None = None
    # the smoother move's centre path (smoother_move; None: the move is not made)
    centre: Float[Array, "T n"] | None = None
    # the joint (theta, path) move's random walk and its adaptation (None: the move is not made)
    rwm_joint: mcmc.RWMState | None = None
    # the system parameters' walk with the measured motion held (system_moves; None: not made);
    # its x follows rwm_joint.x[p:], which holds the chain's system parameters
    rwm_sys: mcmc.RWMState | None = None


#: a move's acceptance in :class:`BlockInfo` where the block does not make it (the output lists none)
NOT_RUN = float("nan")


class BlockInfo(NamedTuple):
    theta: Float[Array, "k p"]
    accept: Float[Array, " k"]
    accept_noncentred: Float[Array, " k"]
    accept_lowfreq: Float[Array, ""]
    accept_residual: Float[Array, ""]
    log_likelihood: Float[Array, ""]
    switch_rate: Float[Array, ""]
    ess: Float[Array, ""]
    force_points: Float[Array, "P nforce"]
    monitored: Float[Array, "M q"]  # displacement, velocity, force at the monitored times
    # the inferred noise standard deviations (the parameters' units) held after each of the block's
    # k MH iterations: the block's draw is made at its last iteration, the ones before hold the
    # previous block's (so they pair with theta as the Gibbs chain's state)
    noise: Float[Array, "k m"]
    accept_noise: Float[Array, " m"]
    accept_smoother: Float[Array, ""]  # the smoother move's acceptance (NaN where it is not made)
    accept_joint: Float[Array, ""]  # the joint (theta, path) move's acceptance (NaN where it is not made)
    # the sampled system parameters (Hyper.sys_names) after the block's joint move, repeated for its k
    # MH iterations (they pair with theta as the Gibbs chain's state)
    system: Float[Array, "k s"]
    # the system parameters' move with the measured motion held (NaN where it is not made)
    accept_system: Float[Array, ""] | None = None
    # the internal states' start-up move (internal_move; NaN where it is not made)
    accept_internal: Float[Array, ""] | None = None
    # the window move (window_move; NaN where it is not made)
    accept_window: Float[Array, ""] | None = None
    # the profile move (profile_move; NaN where it is not made)
    accept_profile: Float[Array, ""] | None = None


class BlockData(NamedTuple):
    """The record and what is precomputed from it (arguments of the compiled programs)."""

    y: Float[Array, "T d"]
    mask: Array
    od: ObservationDensity  # its R: the channels' noise covariance (its inferred entries: ChainState.noise_var)
    ref_q: Float[Array, "T q"]  # centring of the running sums (the smoother's summary quantities)
