"""Mesh generation: the designs (shape, shapes), where rotors and IMUs sit (placement), the
volume meshers (tetmesh: fTetWild, trimesh: Triangle; structured boxes for tests), mirror-
symmetric meshes (mirror) and the surface helpers (surface). Imports no other wing."""
