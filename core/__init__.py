"""QuakeScan core: scene bundles, virtual UAV laser scanning, damage classification.

Headless: never imports bpy.
"""
__version__ = "0.1.0"
