"""Continuous dynamics in Cartesian coordinates: inertia, holonomic constraints, potentials, vector fields."""
