"""Physics: the elements (fem: co-rotated linear, quadratic: P2), the kernels (native loads the
compiled kernels.c and forces.h, reference is their numba twin in the same order and names, fem
picks between them), the integrator (Body: whole control steps) and the physical effects."""
