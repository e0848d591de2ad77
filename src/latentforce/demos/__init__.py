"""Built-in end-to-end cases (``latentforce demo NAME``)."""

from latentforce.demos.nonlinear import run_duffing, run_sine
from latentforce.demos.oma import run_oma

DEMOS = {"oma": run_oma, "duffing": run_duffing, "sine": run_sine}
