"""Acquisition: the sensor registry and the simulated sensors (ray caster, ULS/ALS, DIM) that scan a scene."""
