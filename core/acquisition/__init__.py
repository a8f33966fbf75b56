"""Acquisition: the sensor registry and the simulated sensors (ray caster, ULS/ALS scanner, DIM) that turn a scene into a point cloud."""
