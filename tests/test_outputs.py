"""Strain gauges, load cells and virtual sensors ([[outputs]]) against exact answers."""

import copy

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_kalman import dense_gaussian

import latentforce  # noqa: F401  (enables float64)
from latentforce import estimate, run_checks
from latentforce.errors import LatentForceError
from latentforce.inference.kalman import kalman_smoother
from latentforce.inference.kalman_mcmc import linear_gaussian
from latentforce.inference.mixture import mixture_posterior
from latentforce.inference.smc import ParticleModel
from latentforce.io.config import config_from_dict
from latentforce.io.data import Dataset
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.outputs import OutputSpec, output_matrix, path_outputs
from latentforce.results import read_results, write_results
from latentforce.systems import LinearSystem

M = np.diag([2.0, 1.5])
K = np.array([[30.0, -10.0], [-10.0, 10.0]])
C = np.array([[0.6, -0.2], [-0.2, 0.2]])
PARAMS = dict(M=M, C=C, K=K, force_variance=4.0, force_lengthscale=0.6)


def two_dof_config(outputs=(), method="kalman", sensors=None, **system):
    """A 2-DOF shear-type system, the force at DOF 1, a strain gauge, a load cell, an accelerometer."""
    return {
        "system": {"type": "linear", "M": M.tolist(), "C": C.tolist(), "K": K.tolist(), "force_dofs": [1], **system},
        "force": {"kernel": "matern32", "variance": 4.0, "lengthscale": 0.6},
        "sensors": sensors
        if sensors is not None
        else [
            {"column": "gauge", "quantity": "strain", "coefficients": [-1.0e-3, 1.0e-3], "noise_std": 2e-4},
            {"column": "load", "quantity": "force", "dof": 1, "noise_std": 0.3},
            {"column": "acc0", "quantity": "acceleration", "dof": 0, "noise_std": 0.2},
        ],
        "outputs": list(outputs),
        "inference": {"method": method},
    }


def test_strain_and_force_rows_are_the_readout():
    """The Kalman rows of a strain gauge and a load cell equal the nonlinear readout (model.observe,
    through system.acceleration and the force states) and the particle methods' readout."""
    problem = config_from_dict(two_dof_config(), source="c.toml")
    model = problem.model
    H, R = model.observation(PARAMS)
    x = np.asarray(jax.random.normal(jax.random.key(0), (model.n_state,)))
    np.testing.assert_allclose(H @ x, model.observe(PARAMS, jnp.asarray(x)), rtol=1e-12, atol=1e-12)
    # by hand: strain = c.z, load = u (the single latent force acts at DOF 1)
    u = x[model.force_index()[0]]
    np.testing.assert_allclose((H @ x)[:2], [1e-3 * (x[1] - x[0]), u], rtol=1e-12)
    np.testing.assert_allclose(np.diag(R), [4e-8, 0.09, 0.04])
    pm = ParticleModel(model, PARAMS, 0.05)
    nm = model.n_mech
    np.testing.assert_allclose(
        pm._observe(jnp.asarray(x[:nm]), jnp.asarray(x[nm:])),
        model.observe(PARAMS, jnp.asarray(x)),
        rtol=1e-12,
        atol=1e-14,
    )
    np.testing.assert_allclose(pm.offset(jnp.asarray(x[:nm])) + pm.D @ x[nm:], H @ x, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("gaps", [False, True])
def test_strain_and_force_sensors_smoother_matches_dense_gaussian(gaps):
    """The Kalman smoother with a strain gauge and a load cell (the load cell measured only part of the
    time: NaN gaps) against the dense Gaussian posterior; a load cell with small noise pins the force."""
    problem = config_from_dict(two_dof_config(), source="c.toml")
    model = problem.model
    A, Q, H, R, m0, P0 = linear_gaussian(model, PARAMS, 0.05)
    T = 30
    y = simulate_lg(A, Q, H, R, m0, P0, T, np.random.default_rng(4))
    mask = np.ones((T, 3), bool)
    if gaps:
        mask[5:17, 1] = False  # the load cell off for a while
        y = np.where(mask, y, np.nan)
    ll_dense, mean_dense, cov_dense = dense_scaled(A, Q, H, R, m0, P0, y, mask)
    sm = kalman_smoother(A, Q, H, R, m0, P0, jnp.asarray(y), jnp.asarray(mask))
    assert np.isclose(float(sm.log_likelihood), ll_dense, rtol=1e-9)
    scale = np.sqrt(np.diagonal(cov_dense, axis1=1, axis2=2)).max(axis=0)
    np.testing.assert_allclose(np.asarray(sm.means) / scale, mean_dense / scale, atol=1e-8)
    np.testing.assert_allclose(np.asarray(sm.covs), cov_dense, rtol=1e-6, atol=1e-10 * np.abs(cov_dense).max())
    f = model.force_index()[0]
    sd_f = np.sqrt(np.asarray(sm.covs)[:, f, f])
    seen = mask[:, 1]
    assert np.all(sd_f[seen] < 0.3)  # at most the load cell's noise where it measured
    if gaps:
        assert sd_f[~seen].max() > 2 * sd_f[seen].max()  # and wider in the gap


def simulate_lg(A, Q, H, R, m0, P0, T, rng):
    """A record drawn from the discrete linear-Gaussian model itself (well-conditioned answers)."""
    A, Q, H, R, m0, P0 = map(np.asarray, (A, Q, H, R, m0, P0))
    x = rng.multivariate_normal(m0, P0)
    ys = []
    for _ in range(T):
        ys.append(H @ x + rng.normal(size=H.shape[0]) * np.sqrt(np.diag(R)))
        x = A @ x + rng.multivariate_normal(np.zeros(len(x)), Q, method="eigh")
    return np.array(ys)


def dense_scaled(A, Q, H, R, m0, P0, y, mask):
    """The dense Gaussian with each channel scaled to unit noise: the same posterior, and a
    well-conditioned joint covariance (a strain gauge's 1e-4 next to a force's 1 costs the
    unscaled one ~1e-6 in the log-likelihood); the log-likelihood corrected by the Jacobian."""
    A, Q, H, R, m0, P0 = map(np.asarray, (A, Q, H, R, m0, P0))
    d = 1.0 / np.sqrt(np.diag(R))
    ll, mean, cov = dense_gaussian(A, Q, d[:, None] * H, np.outer(d, d) * R, m0, P0, np.nan_to_num(y) * d, mask)
    return ll + np.sum(np.log(d)[None, :] * mask), mean, cov


def _bad(d, *fragments):
    with pytest.raises(LatentForceError) as info:
        config_from_dict(d, source="config.toml")
    msg = str(info.value)
    assert "config.toml" in msg
    for frag in fragments:
        assert frag in msg, msg


def test_sensor_config_errors():
    d = two_dof_config()
    no_coef = copy.deepcopy(d)
    del no_coef["sensors"][0]["coefficients"]
    _bad(no_coef, "[[sensors]][0].coefficients", "'gauge'", "one per DOF")
    wrong = copy.deepcopy(d)
    wrong["sensors"][0]["coefficients"] = [1.0, 2.0, 3.0]
    _bad(wrong, "[[sensors]][0].coefficients", "3 coefficient(s)", "2 DOF(s)")
    unforced = copy.deepcopy(d)
    unforced["sensors"][1]["dof"] = 0
    _bad(unforced, "[[sensors]][1].dof", "'load'", "no latent force acts there", "force_dofs = [1]")
    stray = copy.deepcopy(d)
    stray["sensors"][2]["coefficients"] = [1.0, 0.0]
    _bad(stray, "[[sensors]][2].coefficients", "'acc0'", "strain")


def test_output_config_errors():
    drift = {"name": "drift", "displacement": [-1.0, 1.0]}
    _bad(two_dof_config([drift, dict(drift)]), "[[outputs]][1].name", "'drift'", "already used by output 0")
    _bad(two_dof_config([{"name": "force", "force": [1.0]}]), "[[outputs]][0].name", "'force'", "taken")
    _bad(two_dof_config([{"name": "displacement_1", "force": [1.0]}]), "[[outputs]][0].name", "taken")
    _bad(two_dof_config([{"name": "hysteretic_force", "force": [1.0]}]), "[[outputs]][0].name", "taken")
    # a parameter's name, fixed or sampled (a sweep found an output "k_0" stored over the stiffness's draws)
    _bad(two_dof_config([{"name": "force_variance", "force": [1.0]}]), "[[outputs]][0].name", "taken by a parameter")
    sampled = two_dof_config([{"name": "force_lengthscale", "force": [1.0]}], method="kalman-mcmc")
    sampled["force"]["lengthscale"] = {"prior": "lognormal", "mu": 0.0, "sigma": 1.0, "init": 0.6}
    _bad(sampled, "[[outputs]][0].name", "'force_lengthscale'", "taken by a parameter")
    _bad(
        two_dof_config([{"name": "drift", "displacement": [1.0]}]),
        "[[outputs]][0].displacement",
        "1 coefficient(s)",
        "2 DOF(s)",
    )
    _bad(two_dof_config([{"name": "shear", "force": [1.0, 2.0]}]), "[[outputs]][0].force", "1 latent force(s)")
    _bad(two_dof_config([{"name": "nothing", "unit": "m"}]), "[[outputs]][0]", "no coefficients")
    _bad(two_dof_config([{"name": "2bad", "force": [1.0]}]), "[[outputs]][0].name", "start with a letter")
    _bad(two_dof_config([{"name": "x", "strain": [1.0, 0.0]}]), "unknown key `strain`", "[[outputs]]")


OUTPUTS = [
    {"name": "drift", "unit": "m", "displacement": [-1.0, 1.0]},
    # the force in storey 0's spring and damper (base shear from the restoring forces)
    {"name": "base_shear", "unit": "N", "displacement": [20.0, 0.0], "velocity": [0.4, 0.0]},
    # sum of inertia forces minus the external force: -(M a)_0 - (M a)_1 + u = base shear by equilibrium
    {"name": "inertia", "unit": "N", "acceleration": [-2.0, -1.5], "force": [1.0]},
    {"name": "acc1", "unit": "m/s^2", "acceleration": [0.0, 1.0]},
]


def _dataset(T=40, seed=2):
    model = config_from_dict(two_dof_config(), source="c.toml").model
    y = simulate_lg(*linear_gaussian(model, PARAMS, 0.05), T, np.random.default_rng(seed))
    mask = np.ones((T, 3), bool)
    mask[8:20, 1] = False
    y[~mask] = np.nan
    return Dataset(np.arange(T) * 0.05, 0.05, y, mask, ["gauge", "load", "acc0"], {})


def test_outputs_under_kalman_match_dense_gaussian(tmp_path):
    """[[outputs]] under kalman: mean and sd to 1e-6 (relative) against the dense Gaussian posterior,
    with the output coefficients built by hand (acceleration = M^-1 (B u - C v - K z))."""
    problem = config_from_dict(two_dof_config(OUTPUTS), source="c.toml")
    ds = _dataset()
    result, _ = estimate.run(problem, ds, seed=0)
    model = problem.model
    A, Q, H, R, m0, P0 = (np.asarray(a) for a in linear_gaussian(model, PARAMS, ds.dt))
    _, mean_dense, cov_dense = dense_scaled(A, Q, H, R, m0, P0, ds.values, ds.mask)
    n, f = model.n_state, model.force_index()[0]
    Minv = np.linalg.inv(M)
    acc = np.zeros((2, n))  # rows of a = M^-1 (B u - C v - K z)
    acc[:, :2] = -Minv @ K
    acc[:, 2:4] = -Minv @ C
    acc[:, f] = Minv @ np.array([0.0, 1.0])
    G = np.zeros((4, n))
    G[0, :2] = [-1.0, 1.0]
    G[1, 0], G[1, 2] = 20.0, 0.4
    G[2] = -2.0 * acc[0] - 1.5 * acc[1]
    G[2, f] += 1.0
    G[3] = acc[1]
    np.testing.assert_allclose(output_matrix(model, problem.outputs, PARAMS), G, rtol=1e-12, atol=1e-12)
    want_mean = mean_dense @ G.T
    want_sd = np.sqrt(np.einsum("ki,tij,kj->tk", G, cov_dense, G))
    for i, spec in enumerate(OUTPUTS):
        got_m, got_s = result.state_mean[spec["name"]][:, 0], result.state_sd[spec["name"]][:, 0]
        np.testing.assert_allclose(got_m, want_mean[:, i], rtol=1e-6, atol=1e-6 * np.abs(want_mean[:, i]).max())
        np.testing.assert_allclose(got_s, want_sd[:, i], rtol=1e-6)
    # cross-covariances matter: the drift's sd is not what independent z0, z1 would give
    naive = np.sqrt(cov_dense[:, 0, 0] + cov_dense[:, 1, 1])
    assert np.max(np.abs(naive / want_sd[:, 0] - 1)) > 0.05
    # equilibrium: the inertia-force output is the base shear, exactly
    np.testing.assert_allclose(result.state_mean["inertia"], result.state_mean["base_shear"], rtol=1e-8, atol=1e-10)

    # the result folder: summary.csv, posterior.nc, summary.json, figures; and back
    write_results(tmp_path / "out", result)
    header = (tmp_path / "out" / "summary.csv").read_text().splitlines()[0].split(",")
    for spec in OUTPUTS:
        assert f"{spec['name']}_mean" in header and f"{spec['name']}_sd" in header
        assert (tmp_path / "out" / "figures" / f"output_{spec['name']}.png").is_file()
    import xarray as xr

    with xr.open_datatree(tmp_path / "out" / "posterior.nc", engine="h5netcdf") as tree:
        v = tree["posterior"]["drift_sd"]
        assert v.attrs["units"] == "m"
        np.testing.assert_allclose(v.values, want_sd[:, 0], rtol=1e-6)
    back = read_results(tmp_path / "out")
    assert back.outputs == {s["name"]: s["unit"] for s in OUTPUTS}
    np.testing.assert_allclose(back.state_mean["acc1"], result.state_mean["acc1"], rtol=1e-15)
    assert set(back.state_mean) == {"displacement", "velocity", "force", *back.outputs}


def test_output_named_like_a_component_reads_back(tmp_path):
    """An output named ``drift_1`` is its own column, not component 1 of a state ``drift``."""
    outputs = [{"name": "drift_1", "displacement": [-1.0, 1.0]}, {"name": "drift", "displacement": [1.0, 0.0]}]
    problem = config_from_dict(two_dof_config(outputs), source="c.toml")
    result, _ = estimate.run(problem, _dataset(T=12), seed=0)
    write_results(tmp_path / "o", result, figures=False)
    back = read_results(tmp_path / "o")
    for name in ("drift", "drift_1"):
        assert back.state_mean[name].shape == (12, 1)
        np.testing.assert_allclose(back.state_sd[name], result.state_sd[name], rtol=1e-15)


def test_outputs_mixture_matches_hand_mixture_of_two_parameter_values():
    """kalman-mcmc's outputs: the mixture over two stiffness values equals the hand mixture
    (mean of G m, mean of G P G^T plus the variance of G m), G depending on the draw."""
    model = LatentForceModel(LinearSystem(), Matern(1), [Sensor("acceleration", 0, 0.2), Sensor("force", 0, 0.5)])
    outputs = (
        OutputSpec("spring", "N", displacement=(1.0,)),  # fixed G
        OutputSpec("acc", "m/s^2", acceleration=(1.0,)),
    )  # G depends on k
    fixed = dict(m=1.0, c=0.4, force_variance=1.0, force_lengthscale=0.5)
    ks = np.array([6.0, 20.0])
    T, dt = 30, 0.05
    y = simulate_lg(*linear_gaussian(model, {**fixed, "k": 10.0}, dt), T, np.random.default_rng(0))
    mask = np.ones((T, 2), bool)
    mask[:10, 1] = False
    y[~mask] = np.nan
    mix = mixture_posterior(jax.random.key(1), model, fixed, {"k": ks[None, :]}, y, mask, dt, outputs=outputs)
    assert mix.n_mix == 2
    means, variances = [], []
    for k in ks:
        params = {**fixed, "k": k}
        A, Q, H, R, m0, P0 = linear_gaussian(model, params, dt)
        sm = kalman_smoother(A, Q, H, R, m0, P0, jnp.asarray(np.nan_to_num(y)), jnp.asarray(mask))
        G = np.zeros((2, model.n_state))
        G[0, 0] = 1.0
        G[1, :] = [-k, -0.4, 1.0, 0.0]  # a = (u - c v - k z) / m by hand
        means.append(np.asarray(sm.means) @ G.T)
        variances.append(np.einsum("ki,tij,kj->tk", G, np.asarray(sm.covs), G))
    means, variances = np.array(means), np.array(variances)
    want_mean = means.mean(0)
    want_sd = np.sqrt(variances.mean(0) + means.var(0))
    for i, spec in enumerate(outputs):
        got_m, got_s = mix.moments[spec.name]
        np.testing.assert_allclose(got_m[:, 0], want_mean[:, i], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(got_s[:, 0], want_sd[:, i], rtol=1e-9)
    # the between-draw variance is part of it (the two k differ enough to matter)
    assert np.max(want_sd / np.sqrt(variances.mean(0))) > 1.02
    # stored paths: the outputs of the stored state paths
    p = mix.paths
    assert p["acc"].shape == p["displacement"].shape
    k_of_path = ks[mix.path_index]
    acc_hand = p["force"][..., 0] - 0.4 * p["velocity"][..., 0] - k_of_path[None, :, None] * p["displacement"][..., 0]
    np.testing.assert_allclose(p["acc"][..., 0], acc_hand, rtol=1e-9, atol=1e-9)


def test_path_outputs_equal_output_matrix_for_linear_systems():
    """The samplers' outputs (acceleration from the equation of motion) equal G x."""
    problem = config_from_dict(two_dof_config(OUTPUTS), source="c.toml")
    model = problem.model
    x = np.asarray(jax.random.normal(jax.random.key(5), (3, 7, model.n_state)))
    G = np.asarray(output_matrix(model, problem.outputs, PARAMS))
    got = path_outputs(model, problem.outputs, PARAMS, x[..., :2], x[..., 2:4], x[..., model.force_index()])
    np.testing.assert_allclose(got, x @ G.T, rtol=1e-10, atol=1e-10)


def test_path_outputs_use_each_draws_own_system_parameters():
    """With sampled system parameters (pgas inferring c and k3 of a Duffing system) every path's
    acceleration comes from its own draw's equation of motion, by hand."""
    from latentforce.systems import Duffing

    model = LatentForceModel(Duffing(), Matern(1), [Sensor("acceleration", 0, 0.1)])
    spec = [OutputSpec("inertia", "N", acceleration=(1.0,))]
    params = dict(m=2.0, c=0.5, k=10.0, k3=100.0, force_variance=1.0, force_lengthscale=0.5)
    z, v, u = (np.asarray(jax.random.normal(jax.random.key(i), (3, 4, 6, 1))) for i in range(3))
    c, k3 = np.linspace(0.1, 1.2, 12).reshape(3, 4), np.linspace(50.0, 400.0, 12).reshape(3, 4)
    got = path_outputs(model, spec, params, z, v, u, draw_params={"c": c, "k3": k3})
    by_hand = (u - c[..., None, None] * v - 10.0 * z - k3[..., None, None] * z**3) / 2.0
    np.testing.assert_allclose(got, by_hand, rtol=1e-12, atol=1e-12)
    fixed = path_outputs(model, spec, params, z, v, u)
    np.testing.assert_allclose(fixed, (u - 0.5 * v - 10.0 * z - 100.0 * z**3) / 2.0, rtol=1e-12, atol=1e-12)


def test_the_gaussian_methods_output_function_is_the_samplers_on_one_state():
    """``output_function`` (ekf/ukf: outputs of one augmented state) against ``path_outputs`` (pgas:
    outputs of paths), two implementations of one definition, on hysteretic systems where the
    acceleration carries the hysteretic force r: a Bouc-Wen oscillator (and by hand) and a 3-storey
    frame with a cubic and a Bouc-Wen element, random states."""
    from latentforce.outputs import output_function
    from latentforce.systems import BoucWen, Element, NonlinearMDOF, ShearFrame

    hyst = dict(alpha=2e3, beta=30.0, gamma=10.0, nu=1.0)
    frame_params = {f"{kind}_{i}": v for kind, v in (("m", 1.5), ("c", 2.0), ("k", 2e3)) for i in range(3)}
    frame_params.update({"element0_k3": 5e4, **{f"element1_{k}": v for k, v in hyst.items()}})
    cases = [
        (BoucWen(), dict(m=2.0, c=0.7, k=40.0, **hyst), 1),
        (
            NonlinearMDOF(ShearFrame(3, force_dofs=(2,)), [Element("cubic", (2, 1)), Element("bouc-wen", (1, 0))]),
            frame_params,
            3,
        ),
    ]
    rng = np.random.default_rng(4)
    for system, params, nd in cases:
        model = LatentForceModel(system, Matern(1), [Sensor("acceleration", 0, 0.1)])
        params = {**params, "force_variance": 1.0, "force_lengthscale": 0.3}
        spec = [
            OutputSpec("inertia", acceleration=tuple(rng.normal(size=nd))),
            OutputSpec("mix", displacement=tuple(rng.normal(size=nd)), velocity=(0.5,) * nd, force=(2.0,)),
        ]
        L = model.layout
        x = rng.normal(size=(6, model.n_state))
        fn = jax.jit(lambda x, p: jax.vmap(output_function(model, spec, p))(x))
        got = np.asarray(fn(jnp.asarray(x), {k: jnp.asarray(v) for k, v in params.items()}))
        z, v, r = (x[:, sl] for sl in (L.displacement, L.velocity, L.internal))
        u = x[:, model.force_index()]
        want = path_outputs(model, spec, params, z, v, u, r=r)
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-9)
        if nd == 1:  # m a = u - c v - k z - r
            acc = (u - 0.7 * v - 40.0 * z - r) / 2.0
            np.testing.assert_allclose(got[:, :1], acc * spec[0].acceleration[0], rtol=1e-11, atol=1e-11)


def test_mass_warning_without_a_force_channel():
    from latentforce.results import RunResult

    def warnings_for(sensors):
        d = two_dof_config(method="kalman-mcmc", sensors=sensors)
        d["system"] = {
            "type": "linear",
            "m": {"prior": "lognormal", "mu": 0.0, "sigma": 0.5, "init": 1.0},
            "c": 0.4,
            "k": 10.0,
        }
        problem = config_from_dict(d, source="c.toml")
        r = RunResult("kalman-mcmc", np.zeros(1), 1, 1, {}, {}, {}, {}, {}, [], 0.0, {})
        run_checks.mass_warning(problem, r)
        return r.diagnostics.get("warnings", [])

    acc = {"column": "a", "quantity": "acceleration", "noise_std": 0.1}
    load = {"column": "f", "quantity": "force", "noise_std": 0.1}
    (msg,) = warnings_for([acc])
    assert "mass (m)" in msg and "force" in msg
    assert warnings_for([acc, load]) == []


def test_no_mass_warning_for_a_mass_carried_from_a_calibration(tmp_path):
    """A monitoring run whose mass prior is a calibration's posterior (which had the load cell)
    is not warned: the mass was identified there."""
    from latentforce.results import RunResult

    d = two_dof_config(method="kalman-mcmc", sensors=[{"column": "a", "quantity": "acceleration", "noise_std": 0.1}])
    d["system"] = {
        "type": "linear",
        "m": {"prior": "lognormal", "mu": 0.0, "sigma": 0.5, "init": 1.0},
        "c": 0.4,
        "k": 10.0,
    }
    problem = config_from_dict(d, source="c.toml")
    for carried, expected in (({"[system].m": {}}, 0), ({"[system].c": {}}, 1)):
        r = RunResult("kalman-mcmc", np.zeros(1), 1, 1, {}, {}, {}, {}, {}, [], 0.0, {})
        run_checks.mass_warning(problem._replace(carried=carried), r)
        assert len(r.diagnostics.get("warnings", [])) == expected, carried


def test_outputs_and_mass_warning_through_kalman_mcmc(tmp_path):
    """kalman-mcmc end to end: the outputs are mixed (in the result, its paths and its files), and a
    run inferring m with only motion measured warns."""
    d = {
        "system": {
            "type": "linear",
            "m": {"prior": "lognormal", "mu": 0.0, "sigma": 0.3, "init": 1.0},
            "c": 0.4,
            "k": 10.0,
        },
        "force": {"kernel": "matern12", "variance": 1.0, "lengthscale": 0.5},
        "sensors": [{"column": "acc", "quantity": "acceleration", "noise_std": 0.2}],
        "outputs": [{"name": "acc_model", "unit": "m/s^2", "acceleration": [1.0]}],
        "inference": {"method": "kalman-mcmc", "iterations": 100, "burn_in": 100, "chains": 2},
    }
    problem = config_from_dict(d, source="c.toml")
    model = problem.model
    T, dt = 40, 0.05
    y = simulate_lg(
        *linear_gaussian(model, dict(m=1.0, c=0.4, k=10.0, force_variance=1.0, force_lengthscale=0.5), dt),
        T,
        np.random.default_rng(3),
    )
    ds = Dataset.from_array(y, dt, ["acc"])
    result, _ = estimate.run(problem, ds, seed=0)
    assert any("no sensor measures the force" in w for w in result.diagnostics["warnings"])
    p = result.path_draws
    m_draw = result.param_draws["m"]
    hand = (p["force"] - 0.4 * p["velocity"] - 10.0 * p["displacement"])[..., 0] / m_draw[:, :, None]
    np.testing.assert_allclose(p["acc_model"][..., 0], hand, rtol=1e-9, atol=1e-9)
    assert result.state_sd["acc_model"].shape == (T, 1) and np.all(result.state_sd["acc_model"] > 0)
    write_results(tmp_path / "o", result, figures=False)
    import xarray as xr

    with xr.open_datatree(tmp_path / "o" / "posterior.nc", engine="h5netcdf") as tree:
        post = tree["posterior"]
        assert post["acc_model"].dims == ("chain", "draw", "time")
        np.testing.assert_allclose(post["acc_model_mean"].values, result.state_mean["acc_model"][:, 0])
        assert post["acc_model_sd"].attrs["units"] == "m/s^2"


def test_a_weakly_identified_parameter_is_named():
    """A posterior barely narrower than its prior is named in a warning; an identified one is not."""
    from latentforce.results import RunResult

    d = two_dof_config(method="kalman-mcmc", sensors=[{"column": "a", "quantity": "acceleration", "noise_std": 0.1}])
    d["system"] = {
        "type": "linear",
        "m": 1.0,
        "c": {"prior": "lognormal", "mu": -1.0, "sigma": 0.5},
        "k": {"prior": "lognormal", "mu": 2.3, "sigma": 1.0},
    }
    problem = config_from_dict(d, source="c.toml")
    rng = np.random.default_rng(0)
    # c: draws from its prior (the data said nothing); k: a posterior 10x narrower than its prior
    draws = {"c": np.exp(-1.0 + 0.5 * rng.normal(size=(4, 500))), "k": np.exp(2.3 + 0.1 * rng.normal(size=(4, 500)))}
    r = RunResult("kalman-mcmc", np.zeros(1), 1, 1, {}, {}, draws, {}, {}, [], 0.0, {})
    run_checks.weak_identification_warning(problem, r)
    (msg,) = r.diagnostics["warnings"]
    assert "weakly identified: c (posterior sd" in msg and "k (" not in msg
    r = RunResult("kalman-mcmc", np.zeros(1), 1, 1, {}, {}, {"k": draws["k"]}, {}, {}, [], 0.0, {})
    run_checks.weak_identification_warning(problem, r)
    assert "warnings" not in r.diagnostics


def test_chains_stuck_apart_are_not_called_weakly_identified():
    """Four chains each narrow but far apart (a run that did not converge, which says so) are not
    'weakly identified': the check reads the spread within chains."""
    from latentforce.results import RunResult

    d = two_dof_config(method="kalman-mcmc", sensors=[{"column": "a", "quantity": "acceleration", "noise_std": 0.1}])
    d["system"] = {"type": "linear", "m": 1.0, "c": 0.5, "k": {"prior": "lognormal", "mu": 2.3, "sigma": 1.0}}
    problem = config_from_dict(d, source="c.toml")
    rng = np.random.default_rng(1)
    centres = np.exp(np.array([0.5, 2.0, 3.5, 5.0]))[:, None]
    draws = {"k": centres * np.exp(0.05 * rng.normal(size=(4, 500)))}
    r = RunResult("kalman-mcmc", np.zeros(1), 1, 1, {}, {}, draws, {}, {}, [], 0.0, {})
    run_checks.weak_identification_warning(problem, r)
    assert "warnings" not in r.diagnostics


def test_unconverged_run_whose_start_found_no_mode_says_so():
    """The start's mode search (kalman_mcmc.start_chains) on a log posterior flat along one parameter
    finds no definite maximum; an unconverged run with that start is warned about it, a converged one
    and a start with a definite mode are not."""
    from latentforce.inference.kalman_mcmc import start_chains
    from latentforce.priors import Flat, LogNormal
    from latentforce.results import RunResult

    def logpost(x, y):  # x[0]: identified (mode at the data's mean); x[1]: the data say nothing, a flat prior
        return -0.5 * ((x[0] - jnp.mean(y)) / 0.1) ** 2 + 0.0 * x[1]

    def logpost_ok(x, y):
        return -0.5 * ((x[0] - jnp.mean(y)) / 0.1) ** 2 - 0.5 * (x[1] - 1.0) ** 2

    priors, inits = (LogNormal(0.0, 1.0), Flat()), np.array([1.0, 2.0])
    data = (jnp.full(50, 1.5),)
    _, _, flat, _ = start_chains(jax.random.key(0), logpost, data, inits, priors, 4)
    _, _, definite, _ = start_chains(jax.random.key(0), logpost_ok, data, inits, priors, 4)
    assert run_checks.start_failed(flat) and not run_checks.start_failed(definite)
    assert not run_checks.start_failed({"method": "init"})  # no search made (use_modes off)
    assert run_checks.start_failed({"laplace_ok": False}) and not run_checks.start_failed({"laplace_ok": True})  # pgas

    def run_with(start, converged):
        r = RunResult("kalman-mcmc", np.zeros(1), 1, 1, {}, {}, {}, {}, {}, [], 0.0, {})
        r.diagnostics["start"], r.convergence = start, {"converged": converged}
        run_checks.start_warning(r)
        return r.diagnostics.get("warnings", [])

    (msg,) = run_with(flat, False)
    assert "found no definite maximum" in msg and "diagnostics.start" in msg
    assert run_with(flat, True) == [] and run_with(definite, False) == []
