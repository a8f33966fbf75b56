"""`quakescan classify --workers N | --scheduler ADDRESS`: the classification as Dask tasks.

The client never holds an epoch. It streams both files chunk by chunk into square blocks
on disk (`quakescan.distributed.blocks`), keeping per building its point counts and x/y box.
Then it asks the workers, each reading only the blocks it needs:

1. the roof-cell counts of every block (the pair's densities, which set the surface
   descriptors' grid: `tasks.block_roof_cells`), and
2. the rows of every tile: the buildings whose pre-event box centre lies in one square of
   the model's tile size, with every point their descriptors read (`tasks.describe_tile_task`).

The tiles, the densities, the registration check's sample and the order of every point are
those of the single-process run, so `buildings.csv` is the same file byte for byte. A
worker that dies has its tasks redone by the scheduler; finished tiles are checkpointed to
OUT/.checkpoint.jsonl (the single-process run's file: either run resumes the other's), and
the block files to OUT/.blocks, valid for one fingerprint of the inputs.
"""
from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np

from ..formats.pointcloud import PointCloudError, check_coordinates_fit_crs
from ..learning import classification as cl
from ..runtime.progress import ProgressCallback
from . import blocks as bk
from .cluster import dashboard_address, dask_client  # noqa: F401  (moved; still importable here)

log = logging.getLogger(__name__)

BLOCK_CELLS = 50  # a block is 50 × 50 density cells (50 m): a 150 m tile reads about 5 × 5 of them
MANIFEST = "manifest.json"
HALO_STEP_M = 10.0  # a tile whose nearest neighbours reach beyond its halo asks again with this much more


class DistributedError(cl.ClassifyError):
    """The distributed classification cannot run as asked."""


def classify_distributed(pre_path, post_path, out_dir, client, *, model_path=None, footprints_path=None,
                         id_field=None, align: bool | None = None, progress: ProgressCallback | None = None,
                         write_las: bool = True, laz: bool | None = None, force: bool = False,
                         block_cells: int = BLOCK_CELLS, chunk_points: int = bk.CHUNK_POINTS,
                         on_stage=None) -> dict:
    """`quakescan.learning.classification.classify` with the tiles described by the workers of
    `client` (a dask.distributed Client). Same files, same rows; the summary adds "dask"."""
    t0 = time.perf_counter()
    out = Path(out_dir)
    model_path = Path(model_path) if model_path else cl.default_model_path()
    for p, what in ((pre_path, "pre-event point cloud"), (post_path, "post-event point cloud"),
                    (footprints_path, "footprint file"), (model_path, "model file")):
        if p is not None and not Path(p).is_file():
            raise cl.ClassifyError(f"{p}: {what} " + ("is a folder, not a file" if Path(p).is_dir() else
                                                      "does not exist"))
    cl._check_output_folder(out, [pre_path, post_path, footprints_path, model_path])
    options = {"id_field": id_field, "write_las": bool(write_las), "laz": laz}
    run_fp = cl._fingerprint(pre_path, post_path, footprints_path, model_path, align, options)
    done = cl._finished(out, run_fp)
    if done is not None and not force:
        return {**done, "up_to_date": True}
    model = cl.load_model(model_path)
    settings = cl.model_settings(model, str(model_path))
    stage = on_stage or (lambda name: None)

    pre_f, post_f = bk.open_epoch_file(pre_path), bk.open_epoch_file(post_path)
    fp = _read_footprints(footprints_path, id_field, pre_f, post_f)
    crs = _pair_crs(pre_f, post_f, fp)
    origin = bk.default_origin(pre_f)
    out.mkdir(parents=True, exist_ok=True)
    store = out / ".blocks"
    sample = None if align is False else cl.check_max_points(align)
    stage("tiling")
    pre_s, post_s = _tiled_epochs(store, run_fp.digest, pre_f, post_f, origin, fp, block_cells, sample, chunk_points)
    if fp is not None and not pre_s.counts:
        b = fp.bounds()
        raise cl.ClassifyError(f"{footprints_path}: no footprint contains a pre-event point (footprints span "
                               f"x {b[:, 0].min():.1f}..{b[:, 2].max():.1f}, y {b[:, 1].min():.1f}..{b[:, 3].max():.1f};"
                               f" points x {[round(pre_f.mins[0], 1), round(pre_f.maxs[0], 1)]}); wrong CRS?")
    if not (set(pre_s.counts) | set(post_s.counts)):
        raise cl.ClassifyError(f"{pre_path}: no point belongs to a building (all building IDs are 0)")
    summary: dict = {"pre": str(pre_path), "post": str(post_path), "model": str(model_path),
                     "model_provenance": model.provenance, "settings": settings.to_json(),
                     "points": {"pre": pre_s.n, "post": post_s.n}, "crs": crs}
    transform, shift = None, 0.0
    if align is False:
        summary["registration"] = {"mode": "off", "checked": False}
    else:
        summary["registration"] = cl.register_samples(pre_s.stable_sample, post_s.stable_sample, None, settings,
                                                      align, summary, post_bounds=np.asarray(post_s.bounds))
        if summary["registration"].get("applied"):
            transform = summary["alignment"]["transform"]
            shift = float(summary["registration"]["offset_m"])
    t_read = time.perf_counter()

    stage("densities")
    geometry = _pair_geometry(client, store, pre_s, post_s, settings, block_cells, transform)
    stage("tiles")
    rows, resumed, widened = _describe_tiles(client, store, pre_s, post_s, settings, geometry, block_cells,
                                             transform, shift, out, run_fp.digest, progress)
    if fp is not None:
        hit = set(pre_s.counts) | set(post_s.counts)
        rows += [cl.BuildingRow(int(b), 0, 0, False, "no point inside the footprint")
                 for b in sorted(int(i) for i in fp.ids if int(i) not in hit)]
        described = {r.building_id for r in rows}
        rows += [cl.BuildingRow(int(b), 0, 0, False, why) for b, why, _ in fp.rejected if int(b) not in described]
    rows.sort(key=lambda r: r.building_id)
    t_describe = time.perf_counter()
    res = cl.predict_rows(rows, model)
    from ..results import writers as results

    outlines = results.building_outlines(res, fp, pre_s.hulls if fp is None else None, (0.0, 0.0))
    cl.write_building_results(out, res, model.grades, fp, outlines, crs, pre_s.map_xy + origin[:2],
                              f"Damage grades: {Path(post_path).name}")
    if write_las:
        stage("graded cloud")
        compress = Path(post_path).suffix.lower() == ".laz" if laz is None else laz
        graded = out / ("post_grades.laz" if compress else "post_grades.las")
        _write_graded_cloud(graded, post_f, origin, crs, fp, transform, {r.building_id: r.grade for r in res},
                            max(post_s.counts, default=0), chunk_points)
        summary["post_grades"] = str(graded)
    counts: dict[str, int] = {}
    for r in res:
        counts[r.label] = counts.get(r.label, 0) + 1
    summary.update({"buildings": len(res), "by_label": counts, "by_grade_name": cl.counts_by_grade_name(res),
                    "resumed_buildings": resumed,
                    "seconds": {"read": round(t_read - t0, 2), "describe": round(t_describe - t_read, 2),
                                "total": round(time.perf_counter() - t0, 2)},
                    "dask": {"workers": len(client.scheduler_info().get("workers", {})),
                             "dashboard": dashboard_address(client), "block_m": bk.block_m(block_cells),
                             "tiles_widened": widened}})
    summary["fingerprint"] = run_fp.digest
    summary["options"] = options
    from ..runtime.atomic import write_text

    write_text(out / "summary.json", json.dumps(summary, indent=1, default=cl._json_default))
    (out / ".checkpoint.jsonl").unlink(missing_ok=True)
    shutil.rmtree(store, ignore_errors=True)
    return summary


def _read_footprints(footprints_path, id_field, pre_f, post_f):
    if footprints_path is None:
        for f in (pre_f, post_f):
            if "building_id" not in f.dimensions:
                raise cl.ClassifyError(f"{f.path}: no building_id dimension; give building footprints "
                                       "(--footprints F.geojson in the clouds' CRS)")
        return None
    from ..formats.footprints import read_footprints

    fp = read_footprints(footprints_path, id_field)
    if fp.crs and pre_f.crs and fp.crs != pre_f.crs:
        raise cl.ClassifyError(f"{footprints_path}: footprints are in {fp.crs} but the point clouds in {pre_f.crs}; "
                               "reproject the footprints")
    return fp


def _pair_crs(pre_f, post_f, fp) -> str | None:
    """The pair's CRS, checked as `check_pair` and `load_pair` check whole epochs."""
    if pre_f.crs and post_f.crs and pre_f.crs != post_f.crs:
        raise PointCloudError(f"{post_f.path}: CRS {post_f.crs} differs from the pre-event epoch's {pre_f.crs} "
                              f"({pre_f.path}); reproject one of them first")
    for f in (pre_f, post_f):
        if f.n == 0:
            raise PointCloudError(f"{f.path}: the point cloud is empty")
        check_coordinates_fit_crs(f.crs, f.mins, f.maxs, f.path)
    a, b = np.array([pre_f.mins[:2], pre_f.maxs[:2]]), np.array([post_f.mins[:2], post_f.maxs[:2]])
    if a[1, 0] < b[0, 0] or b[1, 0] < a[0, 0] or a[1, 1] < b[0, 1] or b[1, 1] < a[0, 1]:
        raise PointCloudError(f"{post_f.path}: no overlap with the pre-event epoch {pre_f.path} "
                              f"(x/y extents {b.round(2).tolist()} vs {a.round(2).tolist()})")
    crs = pre_f.crs or post_f.crs
    if not crs and fp is not None and fp.crs:
        crs = fp.crs
    return crs


def _tiled_epochs(store: Path, digest: str, pre_f, post_f, origin, fp, block_cells, sample, chunk_points):
    """Both epochs as blocks under `store`, streamed now or kept from an interrupted run of
    the same inputs (its manifest is written last)."""
    manifest = bk.read_manifest(store / MANIFEST)
    if manifest and manifest.get("fingerprint") == digest and manifest.get("block_cells") == block_cells:
        try:
            return tuple(bk.EpochStats.from_json(manifest[name], dict(np.load(store / f"{name}.npz")))
                         for name in ("pre", "post"))
        except (OSError, KeyError, ValueError):
            pass  # unreadable: tiled again
    shutil.rmtree(store, ignore_errors=True)
    stats = {}
    for name, f in (("pre", pre_f), ("post", post_f)):
        folder = store / name
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "epoch.json").write_text(json.dumps({"file": f.to_json(), "origin": origin.tolist()}))
        s = bk.stream_epoch(f, origin, folder, block_cells=block_cells, footprints=fp,
                            with_hulls=(name == "pre" and fp is None),
                            sample=None if sample is None else (f.n, sample),
                            map_step=cl.map_step(f.n) if name == "pre" else None, chunk_points=chunk_points)
        arrays = {"stable_sample": s.stable_sample, "map_xy": s.map_xy}
        arrays.update({f"hull_{b}": v for b, v in s.hulls.items()})
        bk.save_arrays(store / f"{name}.npz", arrays)
        stats[name] = s
    bk.write_manifest(store / MANIFEST, {"fingerprint": digest, "block_cells": block_cells,
                                         "pre": stats["pre"].to_json(), "post": stats["post"].to_json()})
    return stats["pre"], stats["post"]


def _pair_geometry(client, store, pre_s, post_s, settings, block_cells, transform):
    """The surface descriptors' grid and cylinder sizes, from the densities the workers count."""
    if settings.surface is None:
        return None
    from ..change.surface import SurfaceGeometry
    from .tasks import block_roof_cells, merge_roof_cells

    def density(name, stats, building_only, moved):
        futures = [client.submit(block_roof_cells, str(store / name), tuple(k), block_cells, building_only,
                                 moved, pure=False) for k in stats.blocks]
        return merge_roof_cells(client.gather(futures))

    d_pre = density("pre", pre_s, True, None)
    d_post = density("post", post_s, True, transform)
    if d_post == 0.0:
        d_post = density("post", post_s, False, transform)
    return SurfaceGeometry.for_pair(settings.surface, d_pre, d_post)


def _describe_tiles(client, store, pre_s, post_s, settings, geometry, block_cells, transform, shift, out, digest,
                    progress):
    from dask.distributed import as_completed

    from ..change.pipeline import quality_gate, rows_by_counts, tile_key
    from .tasks import TileReachError, describe_tile_task

    rows, ok = rows_by_counts(pre_s.counts, post_s.counts, settings)
    halo = _halo(settings, geometry)
    tiles: dict[tuple, list[int]] = {}
    for b in ok:
        tiles.setdefault(tile_key(pre_s.lo[b], pre_s.hi[b], settings.tile_m), []).append(b)
    ckpt = cl._Checkpoint(out / ".checkpoint.jsonl", digest)
    resumed = 0
    total, finished = len(ok), 0
    settings_json = settings.to_json()
    geometry_json = None if geometry is None else dict(geometry.__dict__)
    post_box = np.asarray(post_s.bounds)[:, :2] if post_s.bounds else None

    def spec(key, bids, h):
        lo = np.min([np.minimum(np.asarray(pre_s.lo[b]) - h, np.asarray(post_s.lo.get(b, pre_s.lo[b])) - shift)
                     for b in bids], axis=0)
        hi = np.max([np.maximum(np.asarray(pre_s.hi[b]) + h, np.asarray(post_s.hi.get(b, pre_s.hi[b])) + shift)
                     for b in bids], axis=0)
        return {"key": list(key), "bids": sorted(bids), "box": [lo.tolist(), hi.tolist()], "halo": h,
                "block_cells": block_cells, "read_margin": shift,
                "whole_post_box": None if post_box is None else post_box.tolist()}

    futures, widened = {}, 0
    for key in sorted(tiles):
        bids = tiles[key]
        if all(b in ckpt.rows for b in bids):
            for b in bids:
                rows[b] = ckpt.rows[b]
            resumed += len(bids)
            finished += len(bids)
            if progress:
                progress(finished, total)
            continue
        s = spec(key, bids, halo)
        fut = client.submit(describe_tile_task, str(store), s, settings_json, geometry_json, transform, 1,
                            pure=False, key=f"tile-{key[0]}_{key[1]}-{digest[:8]}")
        futures[fut] = s
    queue = as_completed(list(futures))
    for fut in queue:
        s = futures.pop(fut)
        try:
            result = fut.result()
        except TileReachError as e:  # widen the halo and ask again
            wider = spec(tuple(s["key"]), s["bids"], max(s["halo"] + HALO_STEP_M, e.needed_m + HALO_STEP_M))
            again = client.submit(describe_tile_task, str(store), wider, settings_json, geometry_json, transform,
                                  1, pure=False)
            futures[again] = wider
            queue.add(again)
            widened += 1
            continue
        tile_rows = result["rows"]
        for r in tile_rows:
            r.n_pre, r.n_post = pre_s.counts.get(r.building_id, 0), post_s.counts.get(r.building_id, 0)
            rows[r.building_id] = r
        ckpt.add([r for r in tile_rows if r.assessable])
        finished += len(s["bids"])
        if progress:
            progress(finished, total)
    if resumed:
        log.warning("%s: resuming, %d buildings already described", out, resumed)
    return [quality_gate(rows[b], settings) for b in sorted(rows)], resumed, widened


def _halo(settings, geometry) -> float:
    """How far beyond a tile's buildings its descriptors read (m): the surface descriptors'
    region, the feature radius and a first guess of the nearest-neighbour search."""
    h = 1.0001 * settings.radius_m + HALO_STEP_M
    if settings.surface is not None:
        from ..change.surface import region_margin

        h = max(h, region_margin(settings.surface, geometry) + 1.0)
    return h


def _write_graded_cloud(path, post_f, origin, crs, fp, transform, grade_by_building, max_id, chunk_points):
    """post_grades.las/.laz streamed from the post-event file: its points, aligned as the
    tiles saw them, with every attribute of the file, building ID and grade."""
    import laspy

    from ..change.align import apply_transform
    from ..formats.footprints import assign_buildings
    from ..results.writers import source_chunks_format7, write_grade_las_streamed

    def chunks(reader):
        for raw, kept in source_chunks_format7(reader, chunk_points):
            xyz = post_f.local_xyz(raw.array["X"], raw.array["Y"], raw.array["Z"], origin)
            if fp is None:
                ids = np.asarray(raw["building_id"], dtype=np.int64)
            else:  # IDs from the unaligned points, as the tiles got them
                ids = assign_buildings(xyz[:, 0] + origin[0], xyz[:, 1] + origin[1], fp)
            if transform is not None:
                xyz = apply_transform(transform, xyz)
            yield xyz, ids, kept

    with laspy.open(post_f.path) as reader:
        extra = [(name, reader.header.point_format.dimension_by_name(name).dtype)
                 for name in reader.header.point_format.extra_dimension_names]
        write_grade_las_streamed(path, chunks(reader), origin, crs, grade_by_building, max_id=max_id,
                                 source_extra_dims=extra)


__all__ = ["BLOCK_CELLS", "DistributedError", "classify_distributed", "dashboard_address", "dask_client"]
