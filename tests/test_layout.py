"""The state layout (``model.layout``): the one place that says where each quantity sits."""

import numpy as np
import pytest

import latentforce  # noqa: F401
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.systems import LinearSystem


@pytest.mark.parametrize("ndof,force_dofs,p", [(1, (0,), 0), (2, (1,), 1), (3, (0, 2), 2)])
def test_the_layout_agrees_with_the_state_space_matrices(ndof, force_dofs, p):
    model = LatentForceModel(LinearSystem(ndof, force_dofs), Matern(p), [Sensor("acceleration", ndof - 1, 0.1, "a")])
    L = model.layout
    assert (L.n_mech, L.n_state) == (model.n_mech, model.n_state) == (2 * ndof, 2 * ndof + len(force_dofs) * (p + 1))
    params = (
        {
            "M": np.eye(ndof),
            "C": 0.1 * np.eye(ndof),
            "K": 10.0 * np.eye(ndof),
            "force_variance": 1.0,
            "force_lengthscale": 0.5,
        }
        if ndof > 1
        else {"m": 1.0, "c": 0.1, "k": 10.0, "force_variance": 1.0, "force_lengthscale": 0.5}
    )
    F, W = (np.asarray(a) for a in model.continuous(params))
    # dz/dt = zdot; the force states alone are driven by noise; u_j drives the velocity of its DOF
    np.testing.assert_array_equal(F[L.displacement, L.velocity], np.eye(ndof))
    assert np.all(W[L.mech] == 0) and np.all(np.diag(W)[L.force_states][p :: p + 1] > 0)
    Hu = np.asarray(model.force_matrix())
    np.testing.assert_array_equal(np.argmax(Hu, axis=1), L.force)
    for j, dof in enumerate(force_dofs):
        assert F[L.index("velocity")[dof], L.force[j]] == pytest.approx(1.0)
    x = np.arange(L.n_state, dtype=float)[None]
    z, v, xf = L.split(x)
    q = L.quantities(x)
    np.testing.assert_array_equal(q["displacement"], z)
    np.testing.assert_array_equal(q["velocity"], v)
    np.testing.assert_array_equal(q["force"], x[:, L.force])
    assert xf.shape[-1] == L.n_force_states
