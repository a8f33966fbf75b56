"""QuakeScan's library, imported as `quakescan` (kept in the folder core/): scene bundles,
virtual UAV laser scanning, damage classification.

Headless: never imports bpy.
"""
__version__ = "0.1.0"

import warnings as _warnings

# numba probes TBB first and, finding Debian's older TBB, says so on every parallel kernel's
# first call before falling back to OpenMP: a notice about numba's set-up, not about the
# user's data, which a responder should not have to read. Nothing else is silenced.
_warnings.filterwarnings("ignore", message=r"The TBB threading layer requires TBB version")

# The public API (`quakescan.api`), reached from the package top. Loaded on first use: the
# package itself stays standard-library only, because Blender's own Python imports one of its
# modules (`quakescan.runtime.fingerprint`, the resume rule of the scene generator) without numpy's
# stack; and `import quakescan` stays instant for the command line.
_API = ("acquire", "read_scene", "write_scene", "read_epoch", "read_pair", "describe", "train", "load_model",
        "save_model", "classify", "evaluate", "inject", "sensor_kinds", "Acquired", "BuildingRow", "DamageModel", "Epoch",
        "Evaluation", "PairData", "Scene")
__all__ = ["__version__", *_API]


def __getattr__(name):
    if name in _API:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'quakescan' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API))

