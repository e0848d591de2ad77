"""Built-in end-to-end cases (``latentforce demo NAME``)."""

from latentforce.demos.bouc_wen import run_bouc_wen
from latentforce.demos.duffing_params import run_duffing_params
from latentforce.demos.frame import run_frame
from latentforce.demos.nonlinear import run_duffing, run_sine
from latentforce.demos.oma import run_oma
from latentforce.demos.silverbox import run_silverbox

DEMOS = {
    "oma": run_oma,
    "duffing": run_duffing,
    "duffing-params": run_duffing_params,
    "bouc-wen": run_bouc_wen,
    "frame": run_frame,
    "sine": run_sine,
    "silverbox": run_silverbox,
}
