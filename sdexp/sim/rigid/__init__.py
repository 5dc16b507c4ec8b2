"""Rigid-body analysis: the drone seen as a rigid body (geometry: mass, inertia, rotor wrench,
hover thrust) and held shapes (statics). The privileged knowledge of the rigid baselines."""
