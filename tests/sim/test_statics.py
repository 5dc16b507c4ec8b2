"""Open-loop statics of a soft body: the shape-holding hover thrust (data.hover: shape)."""
import numpy as np

from sdexp.sim.drone import build_drone
from sdexp.sim.rigid.geometry import rest_hover_thrust, rigid_body, wrench_matrix
from sdexp.sim.rigid.statics import deform_reach, hold, shape_hover_thrust
from tests.conftest import make_config


def test_the_shape_hover_carries_the_weight_and_keeps_the_rod_flat(cache_dir):
    """The rod's mass is spread along it, its rotors are not: the rigid hover thrust (weight
    split evenly) curls its ends. The shape-holding thrust differs from it by a pattern with no
    net lift or torque on the rest shape (it still just carries the weight, level), is mirror
    symmetric like the rod, and holds the bends several times smaller."""
    cfg = make_config("drone=rod", f"cache_dir={cache_dir}")
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    rigid = rest_hover_thrust(drone, float(cfg.sim.gravity))
    shape = shape_hover_thrust(drone, cfg.sim)
    fem = drone.fem
    _, _, _, pos, dirs = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(fem.dim))
    W = wrench_matrix(pos, dirs)[[1, 2]]          # 2D: lift and torque
    np.testing.assert_allclose(W @ shape, W @ rigid, atol=1e-6)
    np.testing.assert_allclose((W @ shape)[0], float(cfg.drone.mass) * float(cfg.sim.gravity), rtol=0.02)
    np.testing.assert_allclose(shape, shape[::-1], rtol=1e-2)
    assert np.abs(shape).max() <= drone.max_thrust
    bent_rigid = np.abs(hold(drone, cfg.sim, rigid, 2.0)).max()
    bent_shape = np.abs(hold(drone, cfg.sim, shape, 2.0)).max()
    assert bent_rigid > np.deg2rad(30)
    assert bent_shape < 0.3 * bent_rigid


def test_how_far_the_rotors_can_bend_a_body_that_stays_level(cache_dir):
    """deform_reach: the fleet's deform task asks 15 deg. The 8 m rod (its ends fold under its own
    hover thrust) bends past it; the engine (steel-stiff next to it) bends a few degrees at most,
    the physics behind a failed deform task; the rainbow's two rotors leave no pattern at all (lift
    and tilt take both), so nothing bends it while it stays level."""
    def drone(name):
        cfg = make_config(f"drone={name}", f"cache_dir={cache_dir}")
        return build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element), cfg.sim
    assert deform_reach(*drone("rod")) > 90.0
    assert 0.1 < deform_reach(*drone("engine")) < 5.0
    assert deform_reach(*drone("rainbow")) == 0.0


def test_the_static_hover_lifts_the_weight_of_the_shape_it_bends(cache_dir):
    """static_hover (the design rule's statics): the rod's thrust, trimmed on the shape it bends
    into, lifts its weight with no tilting torque left and a settled fold: the rule holds. The
    same rod with a quarter of its thrust range needs more than 60% of it: the rule names that."""
    from sdexp.sim.rigid.statics import RULE_MAX_SHARE, static_hover
    cfg = make_config("drone=rod", f"cache_dir={cache_dir}")
    drone = build_drone(cfg.drone, cfg.cache_dir, cfg.sim.element)
    hover = static_hover(drone, cfg.sim)
    assert hover.sane and hover.rule() == "", hover
    assert hover.lift_residual < 0.02 and hover.torque_residual < 0.02 and hover.swing_deg < 1.0
    assert 0 < hover.fold_deg < 30 and hover.share < RULE_MAX_SHARE
    weak = make_config("drone=rod", "drone.max_thrust=2.5", f"cache_dir={cache_dir}")
    tight = static_hover(build_drone(weak.drone, weak.cache_dir, weak.sim.element), weak.sim, seconds=1.0)
    assert tight.share > RULE_MAX_SHARE and tight.rule().startswith("largest rotor thrust"), tight
