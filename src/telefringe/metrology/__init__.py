"""Measurements on point clouds: planes, marker spacing, spheres, steps, BGAs."""
