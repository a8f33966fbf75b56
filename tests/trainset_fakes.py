"""A training-set plan whose every table is finished on disk, so that `build` only reads them
(for tests of what build does with tables, not of making them)."""
import numpy as np


def finished_tables(tmp_path, monkeypatch, plan, settings):
    """Write a two-row table (grades 0 and 5) for every pair of `plan` under tmp_path, each with
    the fingerprint build would give it; scene generation is switched off."""
    import quakescan.learning.trainset as ts
    from quakescan.runtime import fingerprint

    fake = {"x": np.zeros((2, len(settings.descriptor_names()))), "y": np.array([0, 5]),
            "building_id": np.array([1, 2]), "density": np.ones((2, 2)), "cells": np.array([50, 60]),
            "seconds": np.zeros(2)}
    monkeypatch.setattr(ts, "generate_city", lambda city, folder: None)
    key = ts._settings_key(settings, plan.labels)
    (tmp_path / "tables").mkdir(parents=True, exist_ok=True)
    for p in plan.pairs:
        scenes = tmp_path / "scenes" / p.city
        for scene in ("pre", p.post_scene):
            (scenes / scene).mkdir(parents=True, exist_ok=True)
            (scenes / scene / "scene.json").write_text("{}")
        np.savez(tmp_path / "tables" / f"{p.name}.{key}.npz", **fake)
        fingerprint.record(tmp_path / "tables" / f"{p.name}.{key}.npz",
                           ts._table_fingerprint(p, scenes, settings, plan.labels))
    return plan
