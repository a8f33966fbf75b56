"""The versions of what the add-on makes, beside the patterns, plans and collapses that change
it (standard library only: the generator reads them before Blender's modules load).

A bundle records the version it was made with (scene.json "generator"); one of another
version is made again, not reused (addon/generation.py `generator_info`, the record compared).
"""

# Bumped whenever the add-on makes different bundles from the same settings. 2: walls another
# building covers are party walls, pattern draws salted by name; physics records name their
# element source. 3: a toppled facade takes the roof strip and the floors that bore on it down
# (roof_drop, sag_depth).
GENERATOR_VERSION = 3
# Bumped whenever collapses by physics (--damage physics|both) differ from the same settings:
# their bundles and part files are then remade, the patterns' bundles stay valid. Absent: 1;
# 2: a collapse stops early once the shards still moving fast hold 1 % of the volume or less.
PHYSICS_VERSION = 2
