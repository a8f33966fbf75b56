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
