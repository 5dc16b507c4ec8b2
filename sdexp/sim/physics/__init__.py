"""Physics: the elements (fem: co-rotated linear, quadratic: P2), the kernels (native loads the
compiled kernels.c, fem holds their numba references and picks between them), the integrator
(Body: whole control steps) and the physical effects."""
