"""Cells of the clouds' frame shared by every stage: the compiled per-cell loops (`cells`) and
the one density measure (`density`). Below formats, acquisition, change, learning and
distributed alike, and importing none of them."""
