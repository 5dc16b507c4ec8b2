"""A rotor's thrust as a uniform traction over its disc (sdexp.sim.mesh.traction), against the
disc's own moments: shares summing to one, centred on the anchor, with the disc's second moment
(r^2 / 2 for a disc, r^2 / 3 for a 2D drone's segment), converging as the mesh refines; linear
and quadratic elements alike."""
import numpy as np
import pytest

from sdexp.sim.mesh.structured import box_tets, box_tris
from sdexp.sim.mesh.traction import disc_weights
from sdexp.sim.physics.quadratic import quadratic_mesh


def plate(dim: int, n: int, quadratic: bool):
    if dim == 3:
        pts, el = box_tets((n, 1, n), (2.0, 0.1, 2.0), (-1.0, -0.1, -1.0))   # the top face at y = 0
    else:
        pts, el = box_tris((n, 1), (2.0, 0.1), (-1.0, -0.1))
    return quadratic_mesh(pts, el) if quadratic else (pts, el)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("quadratic", [False, True])
def test_the_disc_load_has_the_discs_moments_and_converges(dim, quadratic):
    radius = 0.3
    anchor = np.zeros(dim)
    anchor[0] = 0.13                       # off the mesh's vertices
    up = np.eye(dim)[1]
    exact = radius ** 2 / (2.0 if dim == 3 else 3.0)
    errors = []
    for n in (8, 16, 32):
        pts, el = plate(dim, n, quadratic)
        nodes, w = disc_weights(pts, el, anchor, up, radius)
        d = pts[nodes] - anchor
        assert w.sum() == pytest.approx(1.0)
        assert np.allclose(pts[nodes, 1], 0.0)                       # the top face only
        assert np.linalg.norm(w @ d) < 0.02 * radius
        errors.append(abs(w @ np.sum(d ** 2, axis=1) / exact - 1))
    if quadratic:   # the nodes hold d^2 exactly: what is left is the clip at the disc's edge, sampled
        assert max(errors) < 0.025
    else:           # linear interpolation of d^2 overestimates it by O(h^2)
        assert errors[0] > errors[1] > errors[2] and errors[2] < 0.04


def test_a_disc_smaller_than_its_faces_loads_the_nearest_facing_face():
    pts, el = plate(3, 4, False)
    nodes, w = disc_weights(pts, el, np.array([0.1, 0.0, 0.1]), np.array([0.0, 1.0, 0.0]), 1e-4)
    assert len(nodes) == 3 and w.sum() == pytest.approx(1.0) and np.all(w > 0)
