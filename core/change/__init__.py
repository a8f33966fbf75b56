"""Change: from a pre/post pair of clouds to one descriptor row per building (features, split, levels of detection, surfaces)."""
