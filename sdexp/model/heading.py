"""The learned nets in the heading frame (``model.frame: heading``, our extension).

A multicopter's dynamics do not depend on which way it faces: gravity is along +Y, and so is
the outermost Euler angle, the yaw e_y (sdexp.sensing.rotations). Turning a flight about +Y by
any angle changes its yaw and its world-frame horizontal velocities, and nothing else. The
paper's nets read the yaw and the world-frame p_dot, so they can learn a dependence on the
heading that the body does not have: the near-hover data's yaw wanders, and what else moved at
the same time gets attributed to it. On the star (seed 2, hover) the learned g reads 1.0-1.6
rad/s^2 of angular acceleration per radian of yaw, and with the wings' twist (the star's only way
to yaw) this made slow unstable yaw modes that the LQR met with 2.6x gain spikes
(docs/results.md, "The fleet").

In the heading frame the nets cannot: they read the tilt (e_x, e_z) instead of e, and h reads
p_dot turned into the heading frame, Ry(-e_y) p_dot, and predicts the next p_dot there, turned
back by Ry(e_y). d and the vertical channel are as before. Only a 3D drone has a heading;
on a 2D drone (one angle, in the plane) the frame changes nothing.

Functions take NumPy arrays or torch tensors alike (the trainer's arrays, the model's batches).
"""
from __future__ import annotations

import numpy as np

FRAMES = ("world", "heading")
YAW = 1          # e = (e_x, e_y, e_z): e_y, about +Y, is the heading
TILT = (0, 2)    # the angles a heading-frame net reads


def applies(frame: str, n_e: int) -> bool:
    """Whether ``frame`` changes anything for a drone with ``n_e`` Euler angles (3D only)."""
    if frame not in FRAMES:
        raise ValueError(f"frame = {frame!r}: allowed {' or '.join(FRAMES)}")
    return frame == "heading" and n_e == 3


def _lib(v):
    if isinstance(v, np.ndarray):
        return np
    import torch
    return torch


def turn(v, yaw, sign: float = 1.0):
    """Ry(sign * yaw) v for world vectors v (..., 3) and angles yaw (...): sign -1 takes a world
    vector into the heading frame, +1 back (Ry = [[c, 0, s], [0, 1, 0], [-s, 0, c]])."""
    xp = _lib(v)
    c, s = xp.cos(yaw), sign * xp.sin(yaw)
    return xp.stack([c * v[..., 0] + s * v[..., 2], v[..., 1], -s * v[..., 0] + c * v[..., 2]], -1)


def rotation(yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """(Ry(yaw), dRy/dyaw) at one angle, for the chain rule of the model's Jacobian."""
    c, s = np.cos(yaw), np.sin(yaw)
    return (np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]),
            np.array([[-s, 0.0, c], [0.0, 0.0, 0.0], [-c, 0.0, -s]]))
