"""The TOML config: valid files build the right Problem, bad ones give clear errors."""

import copy
import textwrap

import numpy as np
import pytest

from latentforce.errors import LatentForceError
from latentforce.io.config import config_from_dict, data_path, initial_params, load_config
from latentforce.priors import Flat, LogNormal, Normal

SDOF_TOML = """
[data]
path = "accel.csv"
time_column = "t"

[system]
type = "linear"
m = 1.0
c = { prior = "normal", mean = 2.0, sd = 1.0 }
k = { prior = "normal", mean = 105.9, sd = 50.0, init = 100.0 }

[force]
kernel = "matern32"
variance = { prior = "flat", init = 10.0 }
lengthscale = { prior = "lognormal", mu = 0.0, sigma = 2.0, init = 0.2 }

[[sensors]]
column = "acc"
quantity = "acceleration"
noise_std = 0.05

[inference]
method = "kalman-mcmc"
iterations = 200
burn_in = 50
chains = 2
"""

DUFFING = {
    "data": {"path": "d.h5", "sample_rate": 1024.0, "missing": "skip"},
    "system": {"type": "duffing", "m": 1.0, "c": 20.0, "k": 1.0e4, "k3": 1.0e9},
    "force": {
        "kernel": "matern12",
        "variance": {"prior": "flat", "init": 10.0},
        "lengthscale": {"prior": "lognormal", "mu": 0.0, "sigma": 2.0, "init": 0.2},
    },
    "sensors": [
        {"column": "acc", "quantity": "acceleration", "noise_std": 0.05},
        {"column": "disp", "quantity": "displacement", "noise_std": 1e-4},
    ],
    "inference": {"particles": 20, "seed": 3},
}

MDOF = {
    "system": {
        "type": "linear",
        "M": [[1.0, 0.0], [0.0, 2.0]],
        "C": [[0.3, -0.1], [-0.1, 0.2]],
        "K": [[200.0, -100.0], [-100.0, 100.0]],
        "force_dofs": [1],
    },
    "force": {"kernel": "matern52", "variance": 1.0, "lengthscale": 0.5},
    "sensors": [
        {"column": "a0", "quantity": "acceleration", "dof": 0, "noise_std": 0.1},
        {"column": "v1", "quantity": "velocity", "dof": 1, "noise_std": 0.1},
    ],
}


def _write(tmp_path, text, name="config.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_linear_sdof_kalman_mcmc(tmp_path):
    path = _write(tmp_path, SDOF_TOML)
    p = load_config(path)
    assert p.model.ndof == 1 and p.model.n_state == 2 + 2  # matern32 has 2 states
    assert p.fixed == {"m": 1.0}
    assert set(p.free) == {"c", "k", "force_variance", "force_lengthscale"}
    assert p.free["k"].prior == Normal(105.9, 50.0) and p.free["k"].init == 100.0
    assert p.free["c"].init == 2.0  # default init: the normal prior's mean
    assert p.free["force_variance"].prior == Flat()
    assert p.free["force_lengthscale"].prior == LogNormal(0.0, 2.0)
    assert p.columns == ["acc"]
    assert p.model.sensors[0].name == "acc" and p.model.sensors[0].noise_std == 0.05
    assert p.inference.method == "kalman-mcmc" and p.inference.iterations == 200
    assert p.inference.particles is None and p.inference.thin_draws == 200  # defaults (None: "auto")
    assert p.data.path == tmp_path.resolve() / "accel.csv"
    assert p.data.time_column == "t" and p.data.sample_rate is None and p.data.missing == "error"
    assert p.config_path == path.resolve()
    assert p.initial is None
    assert initial_params(p)["k"] == 100.0


def test_data_override_and_default_method(tmp_path):
    text = SDOF_TOML.replace('method = "kalman-mcmc"\n', "")
    p = load_config(_write(tmp_path, text), data_override="elsewhere.csv")
    assert p.data.path.name == "elsewhere.csv" and p.data.path.is_absolute()
    assert p.inference.method == "kalman-mcmc"  # linear with priors


def test_mdof_linear():
    p = config_from_dict(copy.deepcopy(MDOF))
    assert p.model.ndof == 2 and p.model.nforce == 1
    assert p.model.n_state == 2 * 2 + 3  # matern52 has 3 states
    assert p.model.system.force_dofs == (1,)
    np.testing.assert_array_equal(p.fixed["K"], [[200.0, -100.0], [-100.0, 100.0]])
    assert p.free == {} and p.inference.method == "kalman"
    assert p.data.path is None and p.data.time_column == "time"
    with pytest.raises(LatentForceError, match=r"\[data\].path"):
        data_path(p)
    # The model is usable: a 7-state linear model with a stable transition.
    A, Q = p.model.discretise({**p.fixed}, 0.01)
    assert A.shape == (7, 7)


def test_duffing_pgas(tmp_path):
    p = config_from_dict(copy.deepcopy(DUFFING), base_dir=tmp_path)
    assert p.model.system.type_name == "duffing" and p.model.n_state == 3
    assert p.fixed == {"m": 1.0, "c": 20.0, "k": 1.0e4, "k3": 1.0e9}
    assert set(p.free) == {"force_variance", "force_lengthscale"}
    assert p.inference.method == "pgas" and p.inference.particles == 20 and p.inference.seed == 3
    assert p.inference.discretisation == "rk4" and p.inference.proposal == "optimal"
    assert p.data.sample_rate == 1024.0 and p.data.time_column is None and p.data.missing == "skip"
    assert p.columns == ["acc", "disp"]


def test_auto_iterations_need_two_chains(tmp_path):
    """iterations = "auto" stops on R-hat, which compares chains: one chain is refused (it ran to
    max_time and then said R-hat needs two); a fixed count with one chain is allowed."""
    d = _edit(DUFFING, ["inference", "chains"], 1)
    d["inference"].pop("iterations", None)
    with pytest.raises(LatentForceError, match=r"\[inference\]\.chains.*at least 2 chains.*chains = 1"):
        config_from_dict(d, base_dir=tmp_path)
    d["inference"]["iterations"] = 100
    assert config_from_dict(d, base_dir=tmp_path).inference.chains == 1


def test_duffing_pgas_infers_system_parameters(tmp_path):
    """Any of a nonlinear system's parameters may be a prior table under pgas (k, k3 here): free,
    with its prior and init, the others fixed."""
    d = _edit(DUFFING, ["system", "k3"], {"prior": "lognormal", "mu": 20.7, "sigma": 0.5, "init": 8e8})
    d = _edit(d, ["system", "k"], {"prior": "normal", "mean": 1e4, "sd": 1e3})
    p = config_from_dict(d, base_dir=tmp_path)
    assert set(p.free) == {"force_variance", "force_lengthscale", "k", "k3"}
    assert p.fixed == {"m": 1.0, "c": 20.0} and p.free["k3"].init == 8e8
    assert p.inference.method == "pgas"


def test_initial_state():
    d = copy.deepcopy(DUFFING)
    d["initial"] = {"mean": [0.0, 0.0, 0.0], "sd": [1e-3, 1e-3, 1.0]}
    mean, cov = config_from_dict(d).initial
    np.testing.assert_array_equal(cov, np.diag([1e-6, 1e-6, 1.0]))
    full = [[1e-4, 2e-5, 0.0], [2e-5, 1e-3, 1e-3], [0.0, 1e-3, 1.0]]
    d["initial"] = {"mean": [0.1, 0.0, 0.0], "cov": full}
    mean, cov = config_from_dict(d).initial
    np.testing.assert_array_equal(cov, full)
    np.testing.assert_array_equal(mean, [0.1, 0.0, 0.0])


# ----- bad configs ------------------------------------------------------------
def _bad(d, *fragments):
    with pytest.raises(LatentForceError) as info:
        config_from_dict(d, source="config.toml")
    msg = str(info.value)
    assert "config.toml" in msg
    for frag in fragments:
        assert frag in msg, msg
    assert "\n" not in msg
    return msg


def _edit(base, path, value, delete=False):
    d = copy.deepcopy(base)
    node = d
    for part in path[:-1]:
        node = node.setdefault(part, {}) if isinstance(node, dict) else node[part]
    if delete:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return d


def test_steps_per_sample_out_of_range_says_what_is_valid():
    msg = _bad(_edit(DUFFING, ["system", "steps_per_sample"], 9), "[system].steps_per_sample = 9", "1 to 8", '"auto"')
    assert "literal" not in msg


def test_unknown_section_suggests():
    d = copy.deepcopy(DUFFING)
    d["sytem"] = d.pop("system")
    _bad(d, "unknown section [sytem]", "did you mean [system]?", "Valid sections: data, system")


def test_unknown_key_suggests():
    d = _edit(DUFFING, ["sensors", 1, "noise_sd"], 0.1)
    _bad(d, "noise_sd", "did you mean `noise_std`?", "[[sensors]][1]")
    _bad(_edit(DUFFING, ["inference", "partcles"], 10), "partcles", "`particles`")
    _bad(_edit(DUFFING, ["force", "lengthscale", "sgima"], 1.0), "[force].lengthscale.sgima", "`sigma`")


def test_bad_values_name_the_key():
    _bad(_edit(DUFFING, ["system", "m"], -1.0), "[system].m", "mass must be positive", "-1.0")
    _bad(_edit(DUFFING, ["system", "k"], 0), "[system].k", "stiffness")
    _bad(_edit(DUFFING, ["system", "c"], -0.1), "[system].c", "non-negative")
    _bad(_edit(DUFFING, ["system", "m"], "heavy"), "[system].m", "number")
    _bad(_edit(DUFFING, ["system", "k3"], float("nan")), "[system].k3", "finite")
    _bad(_edit(DUFFING, ["sensors", 0, "noise_std"], 0.0), "[[sensors]][0].noise_std", "must be positive")
    _bad(_edit(DUFFING, ["sensors", 0, "quantity"], "jerk"), "[[sensors]][0].quantity", "'acceleration'")
    _bad(_edit(DUFFING, ["sensors", 1, "dof"], 1), "[[sensors]][1].dof", "'disp'", "only DOF 0")
    _bad(_edit(DUFFING, ["sensors", 1, "column"], "acc"), "[[sensors]][1].column", "already used")
    _bad(_edit(DUFFING, ["force", "kernel"], "matern42"), "[force].kernel", "matern12, matern32")
    _bad(_edit(DUFFING, ["force", "variance"], -2.0), "[force].variance", "positive")
    _bad(_edit(DUFFING, ["inference", "particles"], 1), "[inference].particles = 1", "2 or more", '"auto"')
    _bad(_edit(DUFFING, ["inference", "particles"], "many"), "[inference].particles = 'many'", "2 or more")
    for given, settled in (("auto", None), (30, 30)):  # "auto": pgas_defaults.default_particles
        problem = config_from_dict(_edit(DUFFING, ["inference", "particles"], given), source="c")
        assert problem.inference.particles == settled
    _bad(_edit(DUFFING, ["inference", "method"], "mcmc"), "[inference].method", "'pgas'")
    _bad(_edit(DUFFING, ["system", "k3"], None, delete=True), "[system].k3", "required")
    _bad(_edit(DUFFING, ["sensors"], []), "[[sensors]]")
    _bad(_edit(DUFFING, ["sensors"], {"column": "a"}), "[[sensors]]", "array of tables")
    _bad(_edit(DUFFING, ["data", "time_column"], "t"), "[data]", "not both")


def test_system_types():
    _bad(_edit(DUFFING, ["system", "type"], "bouc-wen"), "[system].k3", 'use type = "duffing"')
    _bad(_edit(DUFFING, ["system", "type"], "hysteretic"), "[system].type", "linear, duffing, bouc-wen")
    _bad(_edit(DUFFING, ["system", "type"], "dufing"), "[system].type", "did you mean 'duffing'?")


def test_mdof_matrix_checks():
    _bad(_edit(MDOF, ["system", "M"], [[1.0, 0.0], [0.0, -2.0]]), "[system].M", "positive definite")
    _bad(_edit(MDOF, ["system", "K"], [[1.0, 2.0], [0.0, 1.0]]), "[system].K", "symmetric")
    _bad(_edit(MDOF, ["system", "C"], [[1.0]]), "[system].C", "same size")
    _bad(_edit(MDOF, ["system", "M"], [[1.0, 0.0], [0.0]]), "[system].M", "square")
    _bad(_edit(MDOF, ["system", "force_dofs"], [2]), "[system].force_dofs", "0..1")
    _bad(_edit(MDOF, ["sensors", 1, "dof"], 2), "[[sensors]][1].dof", "'v1'", "0..1")
    _bad(_edit(MDOF, ["system", "m"], 1.0), "[system].m", "not both")


def test_prior_table_checks():
    _bad(_edit(DUFFING, ["force", "variance"], {"prior": "flat"}), "[force].variance.init", "init")
    _bad(
        _edit(DUFFING, ["force", "variance"], {"prior": "cauchy", "init": 1.0}),
        "[force].variance.prior",
        "Valid priors: flat, normal",
    )
    _bad(
        _edit(DUFFING, ["force", "variance"], {"prior": "normal", "mean": 1.0, "init": 1.0}),
        "[force].variance",
        "missing: sd",
    )
    _bad(
        _edit(DUFFING, ["force", "variance"], {"prior": "gamma", "shape": 2.0, "rate": -1.0}),
        "[force].variance",
        "positive",
    )
    _bad(_edit(DUFFING, ["force", "variance"], {"prior": "flat", "init": -1.0}), "[force].variance.init", "positive")


def test_method_consistency():
    _bad(_edit(DUFFING, ["inference", "method"], "kalman"), "[inference].method", "linear", '"pgas"')
    _bad(_edit(DUFFING, ["inference", "method"], "kalman-mcmc"), "[inference].method", "linear")
    d = _edit(MDOF, ["force", "lengthscale"], {"prior": "lognormal", "mu": 0.0, "sigma": 1.0})
    _bad(
        _edit(d, ["inference", "method"], "kalman"), "[inference].method", "fixed", "kalman-mcmc", "[force].lengthscale"
    )
    _bad(_edit(MDOF, ["inference", "method"], "kalman-mcmc"), "[inference].method", "kalman")
    # a linear base with nonlinear elements: the elements are named as what makes it nonlinear
    frame = _edit(MDOF, ["system", "elements"], [{"type": "cubic", "dofs": [1, 0], "k3": 1e4}])
    msg = _bad(_edit(frame, ["inference", "method"], "kalman"), "[inference].method", "[[system.elements]] (cubic)")
    assert "type is 'linear'" not in msg


def test_keys_the_method_does_not_use_are_named():
    """[inference] keys only some methods read (pgas's particles ..., the Kalman methods' kalman): set in the
    file for another method they are ignored, and the problem carries a warning naming them (estimate
    adds it to the run's); keys left at their defaults, or read by the method, give none."""
    ukf = _edit(DUFFING, ["inference"], {"method": "ukf", "particles": 100, "state_every": 3, "kalman": "parallel"})
    (note,) = config_from_dict(ukf, source="config.toml").notes
    for fragment in ("particles, state_every, kalman", "'ukf'", "particles (pgas only)", "kalman (kalman /"):
        assert fragment in note, note
    assert config_from_dict(DUFFING, source="config.toml").notes == ()  # pgas reads particles
    assert config_from_dict(_edit(MDOF, ["inference"], {"kalman": "parallel"}), source="config.toml").notes == ()
    assert "particles" in config_from_dict(_edit(MDOF, ["inference"], {"particles": 8}), source="c.toml").notes[0]


def test_initial_length_explains_state_vector():
    d = copy.deepcopy(DUFFING)
    d["initial"] = {"mean": [0.0, 0.0], "sd": [1.0, 1.0]}
    _bad(d, "[initial].mean", "2 entries", "3", "displacement", "velocit", "force state")
    d["initial"] = {"mean": [0.0] * 3, "sd": [1.0, -1.0, 1.0]}
    _bad(d, "[initial].sd[1]", "greater than or equal to 0")
    d["initial"] = {"mean": [0.0] * 3}
    _bad(d, "[initial]", "either sd", "cov", "neither")
    d["initial"] = {"mean": [0.0] * 3, "sd": [1.0] * 3, "cov": np.eye(3).tolist()}
    _bad(d, "[initial]", "not both")
    d["initial"] = {"mean": [0.0] * 3, "cov": [[1.0, 0.0, 0.0], [0.0, 1.0], [0.0, 0.0, 1.0]]}
    _bad(d, "[initial].cov[1]", "2 entries", "3")
    d["initial"] = {"mean": [0.0] * 3, "cov": [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]}
    _bad(d, "[initial].cov", "not symmetric")
    d["initial"] = {"mean": [0.0] * 3, "cov": [[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]}
    _bad(d, "[initial].cov", "positive semi-definite", "-1")


def test_broken_toml_gives_line(tmp_path):
    path = _write(tmp_path, '[system]\ntype = "linear"\nm = = 1.0\n', name="broken.toml")
    with pytest.raises(LatentForceError) as info:
        load_config(path)
    msg = str(info.value)
    assert "broken.toml" in msg and "line 3" in msg


def test_missing_config_file(tmp_path):
    with pytest.raises(LatentForceError, match="not found"):
        load_config(tmp_path / "nope.toml")


FRAME = {
    "system": {
        "type": "linear",
        "masses": [1.0, 1.0, 1.0],
        "dampings": [0.5, {"prior": "lognormal", "mu": -0.7, "sigma": 1.0}, 0.5],
        "stiffnesses": [{"prior": "lognormal", "mu": 6.0, "sigma": 0.5, "init": 400.0}, 400.0, 400.0],
        "force_dofs": [2],
    },
    "force": {"kernel": "matern32", "variance": 1.0, "lengthscale": 0.5},
    "sensors": [{"column": "a0", "quantity": "acceleration", "dof": 0, "noise_std": 0.05}],
}


def test_shear_frame_lists_give_named_storey_parameters():
    from latentforce.systems import ShearFrame

    p = config_from_dict(FRAME)
    assert isinstance(p.model.system, ShearFrame) and p.model.ndof == 3
    assert set(p.free) == {"c_1", "k_0"} and p.inference.method == "kalman-mcmc"
    params = dict(p.fixed, c_1=0.25, k_0=500.0)
    M, C, K = (np.asarray(a) for a in p.model.system.matrices(params))
    np.testing.assert_array_equal(M, np.eye(3))
    np.testing.assert_array_equal(K, [[900.0, -400.0, 0.0], [-400.0, 800.0, -400.0], [0.0, -400.0, 400.0]])
    np.testing.assert_array_equal(C, [[0.75, -0.25, 0.0], [-0.25, 0.75, -0.5], [0.0, -0.5, 0.5]])
    _bad(_edit(FRAME, ["system", "dampings"], [0.5, 0.5]), "[system].dampings", "2 entries", "3")
    _bad(_edit(FRAME, ["system", "stiffnesses", 1], -1.0), "[system].stiffnesses[1]", "positive")
    _bad(_edit(FRAME, ["system", "K"], [[1.0]]), "[system].K", "lists")
    _bad(_edit(FRAME, ["system", "force_dofs"], [3]), "[system].force_dofs", "outside")
    d = _edit(FRAME, ["inference"], {"method": "kalman"})
    _bad(d, "[inference].method", "[system].dampings[1]")
