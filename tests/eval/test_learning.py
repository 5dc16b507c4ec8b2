"""model.prior: the learned model on top of the rest shape as a rigid body (shrunk: the rod's
800 transitions)."""
import numpy as np
import pytest

from sdexp.errors import UserError
from sdexp.eval.flights import Setup
from sdexp.model.identification import identify
from sdexp.sim.rigid.geometry import rigid_body, rigid_prior
from tests.conftest import make_config
from tests.eval.references import SHRUNK


def test_the_rigid_prior_is_the_rest_shapes_response_and_the_nets_learn_the_rest(cache_dir):
    cfg = make_config(*SHRUNK, f"cache_dir={cache_dir}", "model.prior=rigid")
    setup = Setup(cfg, progress=False)
    drone, nets = setup.drone, setup.trained.nets
    prior = rigid_prior(drone, float(cfg.sim.gravity))
    lift, weight = prior["p_dot_next"]
    fem = drone.fem
    mass = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(2))[0]
    # the rod's five rotors point up: each newton lifts 1/mass, the weight pulls g down
    np.testing.assert_allclose(lift[1], 1.0 / mass, rtol=1e-3)
    np.testing.assert_allclose(weight, [0, -9.81])
    assert nets["h"].has_prior and nets["g"].has_prior and not nets["d"].has_prior
    plain = Setup(make_config(*SHRUNK, f"cache_dir={cache_dir}"), progress=False)
    assert plain.trained.key != setup.trained.key and not plain.trained.nets["h"].has_prior
    # the learned B (Eq. 6) carries the prior: it is part of what the nets' residual is added to
    x, u = setup.simulator().state(noisy=False).x, np.full(drone.num_rotors, 2.0)
    _, B = setup.dyn.jacobians(x, u)
    assert np.all(np.isfinite(B))


def test_a_prior_needs_the_experiments_side(cache_dir):
    with pytest.raises(UserError) as err:
        identify(make_config(*SHRUNK, f"cache_dir={cache_dir}", "model.prior=rigid"), progress=False)
    assert "model.prior = rigid" in str(err.value) and "model.prior=none" in str(err.value)
