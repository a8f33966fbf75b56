"""Change: from a pre/post pair to one descriptor row per building (features, split, LoD, M3C2, surfaces)."""
