"""The convergence verdict on chains whose answer is known: iid draws, stuck chains, short runs."""

import numpy as np
import pytest

from latentforce.inference import convergence


def _iid(rng, chains=4, draws=1000):
    return rng.standard_normal((chains, draws))


def test_well_mixed_chains_are_converged():
    rng = np.random.default_rng(0)
    record = convergence.diagnose({"k": _iid(rng), "c": _iid(rng)})
    assert record["converged"], record
    assert record["max_r_hat"] < 1.01 and record["min_ess_bulk"] > 3000
    assert convergence.warning_message(record, "kalman-mcmc") is None


def test_chains_stuck_apart_are_not_converged_and_named():
    rng = np.random.default_rng(1)
    stuck = _iid(rng) + np.array([0.0, 0.0, 0.0, 3.0])[:, None]  # one chain in another mode
    record = convergence.diagnose({"k": _iid(rng), "force_variance": stuck})
    assert not record["converged"]
    assert record["worst"][0]["name"] == "force_variance" and record["max_r_hat"] > 1.2
    message = convergence.warning_message(record, "pgas")
    assert message.startswith("NOT CONVERGED") and "force_variance" in message and "\n" not in message


def test_autocorrelated_chains_below_the_target_ess_are_not_converged():
    rng = np.random.default_rng(2)
    # AR(1) with phi = 0.99: bulk ESS about 4 * 1000 * (1 - phi) / (1 + phi) = 20
    x = np.zeros((4, 1000))
    for t in range(1, 1000):
        x[:, t] = 0.99 * x[:, t - 1] + rng.standard_normal(4)
    record = convergence.diagnose({"k": x, "c": _iid(rng)})
    assert not record["converged"] and record["min_ess_bulk"] < 100
    assert record["worst"][0]["name"] == "k"
    # The same chains pass a target they do reach.
    assert convergence.diagnose({"c": _iid(rng)}, target_ess=100)["converged"]


def test_one_chain_or_too_few_draws_cannot_show_convergence():
    rng = np.random.default_rng(3)
    record = convergence.diagnose({"k": _iid(rng, chains=1, draws=5000)})
    assert not record["converged"] and "2 chains" in record["reason"]
    record = convergence.diagnose({"k": _iid(rng, chains=4, draws=3)})
    assert not record["converged"] and "too few draws" in record["reason"]


def test_states_decide_or_inform():
    rng = np.random.default_rng(4)
    paths = {"force": rng.standard_normal((4, 600, 100, 1)), "displacement": rng.standard_normal((4, 600, 100, 1))}
    paths["force"][3, :, 52, 0] += 2.0  # one chain differs at one monitored time
    times = convergence.monitored_times(100)
    assert len(times) >= 20 and times[0] == 0 and times[-1] == 99 and 52 in times
    states = convergence.state_quantities(paths, times, np.arange(100) * 0.5)
    assert "force[t=26]" in states and len(states) == 2 * len(times)
    params = {"k": _iid(rng, draws=600)}
    decided = convergence.diagnose(params, states)
    assert not decided["converged"] and decided["worst"][0]["name"] == "force[t=26]"
    informed = convergence.diagnose(params, states, states_decide=False)
    assert informed["converged"] and informed["states"]["max_r_hat"] > 1.2
    assert informed["states"]["monitored"] == len(states) and not informed["states"]["decide"]


def test_a_constant_quantity_is_left_out_of_the_verdict():
    rng = np.random.default_rng(5)
    record = convergence.diagnose({"k": _iid(rng), "pinned": np.ones((4, 1000))})
    assert record["converged"] and np.isnan(convergence.quantity_stats({"p": np.ones((4, 10))})["p"]["r_hat"])


def test_a_chain_that_diverged_to_nan_is_not_converged_and_named():
    """A NaN path's R-hat is NaN like a constant's: without its own check it would leave the verdict
    and the three good chains alone would say converged."""
    rng = np.random.default_rng(6)
    force = _iid(rng)
    force[2, 300:] = np.nan  # chain 2 diverged a third of the way in
    record = convergence.diagnose({"k": _iid(rng)}, {"force[t=1]": force, "force[t=2]": _iid(rng)})
    assert not record["converged"]
    assert "non-finite draws in 1 quantities (force[t=1]) on chain(s) 2" in record["reason"]
    assert record["diverged_chains"] == [2]
    message = convergence.warning_message(record, "pgas", "; here HINT")
    assert "a chain diverged" in message and "running longer does not help" in message
    assert message.endswith("; here HINT.") and "use more particles" not in message
    healthy = convergence.diagnose({"k": _iid(rng)}, {"force[t=1]": _iid(rng), "force[t=2]": _iid(rng)}, rhat_max=1.0)
    assert "diverged_chains" not in healthy and "running longer does not help" not in convergence.warning_message(
        healthy, "pgas", "; here HINT"
    )
    # states that only inform (Kalman methods) do not decide, NaN or not
    assert convergence.diagnose({"k": _iid(rng)}, {"force[t=1]": force}, states_decide=False)["converged"]


@pytest.mark.parametrize("T,n", [(5, 24), (1000, 24), (10, 3)])
def test_monitored_times_are_spread_and_unique(T, n):
    times = convergence.monitored_times(T, n)
    assert len(times) == min(n, T) and np.all(np.diff(times) > 0) and times[-1] == T - 1


def test_a_pgas_warning_names_a_sweep_that_hardly_switched():
    """An unconverged pgas run whose ancestor switch rate is below LOW_SWITCH_RATE, and whose smoother
    move did not renew the path either, gets the likely cause and what to do appended to its warning;
    otherwise (or with the rate unknown), nothing."""
    from latentforce.estimate_particles import LOW_SMOOTHER_ACCEPTANCE, LOW_SWITCH_RATE, low_switch_advice

    text = low_switch_advice(0.008, 0.0)
    assert "0.008" in text and "displacement" in text and "Matérn-1/2" in text and "ukf" in text
    assert "smoother move (acceptance 0.000)" in text
    assert "\n" not in text
    assert low_switch_advice(LOW_SWITCH_RATE, 0.0) == "" and low_switch_advice(0.6, 0.0) == ""
    assert low_switch_advice(float("nan")) == ""
    # the smoother move renewed the path: the sweep's low rate is not the cause
    assert low_switch_advice(0.008, LOW_SMOOTHER_ACCEPTANCE) == "" and low_switch_advice(0.008, 0.9) == ""
    assert low_switch_advice(0.008) != ""  # acceptance unknown (no move): the advice stands
    # with a displacement or strain channel the advice is not to add one, but where the move fails
    text = low_switch_advice(0.008, 0.02, displacement_measured=True)
    assert "add a displacement sensor" not in text and "substeps" in text and "ukf" in text
    assert low_switch_advice(0.008, 0.9, displacement_measured=True) == ""
    # a Matérn-1/2 force model: no blame on smoothness, no advice to use the model already used; the
    # sweep still mixes at these rates, slowly, so a longer run is the advice
    for measured in (False, True):
        text = low_switch_advice(0.06, 0.003, displacement_measured=measured, smooth_force=False)
        assert "Matérn-1/2 force model" not in text and "weakness of a smooth force" not in text
        assert "max_time" in text and "helps little" not in text and "ukf" in text and "\n" not in text
    assert "coarsely" in low_switch_advice(0.06, 0.003, displacement_measured=True, smooth_force=False)


def test_a_pgas_warning_names_an_unmeasured_displacement_when_it_is_the_slowest():
    """An unconverged pgas run whose worst quantity is a displacement, with no displacement or strain
    channel, gets the advice to add one (velocity alone at Matérn-5/2: the smoother move accepts, so the
    low-switch advice says nothing); a measured displacement, another worst quantity, a converged run or
    a diverged chain get nothing."""
    from latentforce.estimate_particles import unmeasured_displacement_advice

    def record(*names, **extra):
        return {"converged": False, "worst": [{"name": n, "r_hat": 1.2, "ess_bulk": 15.0} for n in names], **extra}

    slow = record("displacement[t=0.44]", "force[t=0.33]")
    text = unmeasured_displacement_advice(slow, False)
    assert "displacement (or strain) sensor" in text and "ukf" in text and "\n" not in text
    assert unmeasured_displacement_advice(record("displacement_1[t=2]"), False) == text  # MDOF names
    assert unmeasured_displacement_advice(slow, True) == ""  # measured: the cause is elsewhere
    assert unmeasured_displacement_advice(record("force[t=0.33]", "displacement[t=0.44]"), False) == ""
    assert unmeasured_displacement_advice(record("force_variance"), False) == ""
    assert unmeasured_displacement_advice(record(), False) == ""
    assert unmeasured_displacement_advice({**slow, "converged": True}, False) == ""
    assert unmeasured_displacement_advice(record("displacement[t=1]", diverged_chains=[2]), False) == ""


def test_smooth_force_reads_the_kernels_terms():
    from latentforce.estimate_particles import kernel_is_smooth
    from latentforce.kernels import Matern

    assert not kernel_is_smooth(Matern(0)) and kernel_is_smooth(Matern(1)) and kernel_is_smooth(Matern(3))
    assert not kernel_is_smooth(Matern(0) + Matern(0)) and kernel_is_smooth(Matern(0) + Matern(2))


def test_a_pgas_warning_names_the_initial_hysteretic_force_when_the_record_start_is_slow():
    """An unconverged pgas run on a system with hysteretic states, no [initial] given, whose worst
    three quantities include one within the record's first 5 % (by time index, before the times are
    labelled) gets the [initial] advice; a slow quantity later only, a converged run, a system
    without hysteresis or a given [initial] get nothing."""
    from latentforce.estimate_particles import hysteretic_start_advice

    def record(*names, converged=False):
        return {"converged": converged, "worst": [{"name": n, "r_hat": 1.8, "ess_bulk": 6.0} for n in names]}

    slow_start = record("force[t=351]", "force[t=20]", "hysteretic_force[t=0]")
    text = hysteretic_start_advice(slow_start, True, False, 450)
    assert "[initial]" in text and "hysteretic force" in text and "virgin" in text and "\n" not in text
    # the first 5 % of 450 samples: indices up to 23
    assert hysteretic_start_advice(record("force[t=23]"), True, False, 450) != ""
    assert hysteretic_start_advice(record("force[t=24]", "velocity[t=300]"), True, False, 450) == ""
    # only the worst three count
    assert hysteretic_start_advice(record("a[t=200]", "b[t=300]", "c[t=400]", "force[t=0]"), True, False, 450) == ""
    assert hysteretic_start_advice(record("force_variance", "force[t=100]"), True, False, 450) == ""
    assert hysteretic_start_advice(slow_start, False, False, 450) == ""  # no hysteretic state
    assert hysteretic_start_advice(slow_start, True, True, 450) == ""  # the user gave [initial]
    converged = record("force[t=0]", converged=True)
    assert hysteretic_start_advice(converged, True, False, 450) == ""


def test_a_negative_cubic_stiffness_is_named_where_a_model_overflowed():
    """A softening cubic (k3 < 0: a Duffing's, an element's, fixed or among the draws) is the likely
    cause a diverged run's message names, by its config key; positive ones are not named."""
    from latentforce.estimate_particles import softening_hint

    hint = softening_hint({"k3": -2.0e5, "element1_k3": np.array([[3.0, -1.0]]), "element0_k3": 2.5e7, "k": 1e4})
    assert "[system].k3 = -2e+05" in hint and "[[system.elements]][1].k3 = -1" in hint
    assert "[[system.elements]][0]" not in hint and hint.startswith("; here a cubic stiffness is negative")
    assert softening_hint({"k3": 4e4, "element0_k3": np.array([1.0, 2.0]), "k": -1.0}) == ""


def test_a_failing_r_hat_is_never_printed_as_passing():
    record = {"converged": False, "max_r_hat": 1.0104, "r_hat_max": 1.01, "min_ess_bulk": 500.0, "target_ess": 400.0}
    assert "R-hat 1.0104 (need <= 1.01)" in convergence.warning_message(record, "ekf")
    assert "R-hat 1.340 (need" in convergence.warning_message({**record, "max_r_hat": 1.34}, "ekf")


def test_chains_stuck_apart_are_not_told_to_run_longer():
    """A worst R-hat of 3e16 (proposals never accepted, chains at their starts) is printed as "> 100" and
    the advice is about the model, not about running longer."""
    record = {
        "converged": False,
        "max_r_hat": 3.2e16,
        "r_hat_max": 1.01,
        "min_ess_bulk": 2.0,
        "target_ess": 400.0,
        "worst": [{"name": "k3", "r_hat": 3.2e16, "ess_bulk": 2.0}],
    }
    message = convergence.warning_message(record, "pgas")
    assert "R-hat > 100 (need" in message and "k3 (R-hat > 100," in message and "3.2e" not in message
    assert "running longer will not help" in message and "run longer" not in message.replace("running longer", "")
