"""latentforce: Bayesian joint input-state(-parameter) estimation with
Gaussian-process latent force models.

The package enables float64 in JAX on import: the Kalman recursions and the
stiff, lightly damped structural models we target lose too much precision in
float32. It also raises XLA CPU's small-loop threshold in ``XLA_FLAGS``
before JAX starts its backend (:mod:`latentforce.compile`): import
latentforce before running JAX computations to get it.
"""

import jax

from latentforce.compile import raise_small_loop_threshold

raise_small_loop_threshold()
jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"

from latentforce.errors import LatentForceError  # noqa: E402

__all__ = ["LatentForceError", "__version__"]
