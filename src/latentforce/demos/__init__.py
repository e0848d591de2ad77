"""Built-in end-to-end cases (``latentforce demo NAME``)."""

from latentforce.demos.oma import run_oma

DEMOS = {"oma": run_oma}

try:  # the nonlinear demos need the PGAS sampler
    from latentforce.demos.nonlinear import run_duffing, run_sine

    DEMOS.update({"duffing": run_duffing, "sine": run_sine})
except ImportError:  # pragma: no cover
    pass
