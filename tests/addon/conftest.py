"""Add-on tests: pure-Python parts run anywhere; Blender parts through the bpy module.

The add-on is registered once per session (its own register()); tests that touch Blender
data reset the file with read_homefile(use_empty=True, use_factory_startup=True).
"""
import importlib.util
import shutil
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

HAVE_BPY = importlib.util.find_spec("bpy") is not None
BLENDER = shutil.which("blender")


@pytest.fixture(scope="session")
def bpy_registered():
    """bpy imported and the add-on registered (once)."""
    bpy = pytest.importorskip("bpy")
    import addon
    registered_here = False
    if not hasattr(bpy.types.Object, "qs_building"):
        addon.register()
        registered_here = True
    yield bpy
    if registered_here:
        addon.unregister()


@pytest.fixture
def blank(bpy_registered):
    """An empty Blender file (add-on still registered)."""
    bpy = bpy_registered
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    yield bpy
