"""Scenes and files: scene bundles, CityJSON import, synthetic cities, LAS/LAZ epochs, footprints."""
