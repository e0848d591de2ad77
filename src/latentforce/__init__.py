"""latentforce: Bayesian joint input-state(-parameter) estimation with
Gaussian-process latent force models.

Importing the package changes no JAX setting and no environment variable.
Its computations need float64 (the Kalman recursions and the stiff, lightly
damped structural models we target lose too much precision in float32), so
a program that uses the library calls :func:`enable_x64` once, first thing,
as with ``numpyro.enable_x64()``::

    import latentforce
    latentforce.enable_x64()

The command line does this itself. Entry points that need float64 (building
a model, :func:`latentforce.estimate.run`, :func:`latentforce.simulate.simulate`)
refuse to run without it, with a message saying so.
"""

__version__ = "0.1.0"

from latentforce.errors import LatentForceError  # noqa: E402


def enable_x64() -> None:
    """Switch JAX to float64 for the whole process, and, if JAX has not started its CPU
    backend yet, raise XLA CPU's small-loop threshold in ``XLA_FLAGS``
    (:func:`latentforce.compile.raise_small_loop_threshold`: batched path moves run
    about 2x faster with it; a backend already started, or backend options of your own
    in ``XLA_FLAGS``, are left alone). Call it before any JAX computation."""
    import jax

    from latentforce.compile import raise_small_loop_threshold

    raise_small_loop_threshold()
    jax.config.update("jax_enable_x64", True)


__all__ = ["LatentForceError", "__version__", "enable_x64"]
