"""The reduced-order co-rotated model (sim.model = reduced): a floating frame, a mass-orthonormal
deformation basis and co-rotated forces at a cubature set of elements, built per drone from its
full FEM (which stays the reference). Nothing above sdexp.sim knows which model runs."""
