"""COPC input read by bounds (`quakescan.formats.copc`): every point once, in file order; a
tile's box read from the file's nodes is the box read from block files; a real pair as COPC
classified on two workers writes the files one process writes."""
import filecmp

import laspy
import numpy as np
import pytest

from tests.copc_files import write_copc
from tests.scenes import scan_box_pair


@pytest.fixture(scope="module")
def box_copc(tmp_path_factory):
    d = tmp_path_factory.mktemp("copc")
    scan_box_pair(d, (9.0, 4.0, 9.0, 3.0, 9.0, 12.0))
    return write_copc(d / "pre.las", d / "pre.copc.laz"), d


def test_a_copc_file_is_read_node_by_node_as_laspy_reads_it_whole(box_copc):
    from quakescan.distributed.streaming import open_epoch_file
    from quakescan.formats.copc import copc_index

    path, _ = box_copc
    index = copc_index(path)
    assert len(index.nodes) > 9  # the root, its children and grandchildren: several levels hold points
    whole = laspy.read(path)
    packed, where = index.points_in_nodes(index.nodes)
    np.testing.assert_array_equal(where, np.arange(whole.header.point_count))
    for dim in ("X", "Y", "Z", "building_id"):
        np.testing.assert_array_equal(packed[dim], np.asarray(whole.points.array[dim]), err_msg=dim)
    assert open_epoch_file(path).copc and not open_epoch_file(path.parent / "pre.las").copc


@pytest.mark.parametrize("frac", [(0.0, 1.0), (0.3, 0.6), (0.45, 0.47)])
def test_a_box_read_from_the_copc_file_is_the_box_read_from_block_files(box_copc, tmp_path, frac):
    """The same COPC epoch tiled twice: by bounds from the file (no block files), and as a
    plain LAZ into block files. Every box and block read gives the same records, in the same
    order, to the last bit."""
    import json
    from dataclasses import replace

    from quakescan.distributed.block_store import RECORD
    from quakescan.distributed.reading import read_box, read_records
    from quakescan.distributed.streaming import default_origin, open_epoch_file, stream_epoch

    path, _ = box_copc
    f = open_epoch_file(path)
    origin = default_origin(f)
    cells = 7
    stats = {}
    for name, epoch in (("copc", f), ("blocks", replace(f, copc=False))):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "epoch.json").write_text(json.dumps({"file": epoch.to_json(), "origin": origin.tolist(),
                                                       "parts": 0, "block_cells": cells, "footprints": None}))
        stats[name] = stream_epoch(epoch, origin, folder, block_cells=cells, chunk_points=40_000)
    assert not list((tmp_path / "copc").glob("*.bin")) and list((tmp_path / "blocks").glob("*.bin"))
    assert stats["copc"].counts == stats["blocks"].counts and stats["copc"].blocks == stats["blocks"].blocks
    xy = laspy.read(path).xyz[:, :2] - origin[:2]
    box = np.array([np.quantile(xy, frac[0], axis=0), np.quantile(xy, frac[1], axis=0)])
    a = read_box(tmp_path / "copc", f, origin, box, cells)
    b = read_box(tmp_path / "blocks", replace(f, copc=False), origin, box, cells)
    assert len(a[0]) > 0
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    keys = [tuple(k) for k in stats["copc"].blocks[::3]]
    for only in (False, True):
        # the COPC records are the widest, the blocks' the narrowest the file allows: equal values
        np.testing.assert_array_equal(read_records(tmp_path / "copc", keys, only),
                                      read_records(tmp_path / "blocks", keys, only).astype(RECORD))
    # the densities' roof cells of a group of blocks: the group's box read from the file once
    from quakescan.distributed.tasks import group_roof_cells

    group = [tuple(k) for k in stats["copc"].blocks[:16]]
    assert group_roof_cells(str(tmp_path / "copc"), group, cells) == \
        group_roof_cells(str(tmp_path / "blocks"), group, cells)
    # and a square of blocks counted as one part
    square = [k for k in group if k[0] // 4 == group[0][0] // 4 and k[1] // 4 == group[0][1] // 4]
    assert group_roof_cells(str(tmp_path / "copc"), square, cells, square_cells=4 * cells) == \
        group_roof_cells(str(tmp_path / "blocks"), square, cells, square_cells=4 * cells)


@pytest.mark.realdata
@pytest.mark.slow
def test_real_halves_as_copc_with_footprints_classify_on_two_workers_as_one_process(shared_data, tmp_path):
    """AHN3 tile 2 as two random halves (seed 5), each written as COPC: building IDs come from
    the footprints, in the tile tasks; both runs write the same files, byte for byte."""
    distributed = pytest.importorskip("distributed")
    from quakescan.distributed.engine import classify_distributed
    from quakescan.assessment.run import classify

    las = laspy.read(shared_data / "ahn3_cropped_2.laz")
    half = np.random.default_rng(5).random(las.header.point_count) < 0.5
    pair = []
    for name, keep in (("a", half), ("b", ~half)):
        part = laspy.LasData(las.header)
        part.points = las.points[keep]
        part.write(tmp_path / f"{name}.las")
        pair.append(write_copc(tmp_path / f"{name}.las", tmp_path / f"{name}.copc.laz", seed=ord(name)))
    fp = shared_data / "ahn3_footprints_rd.geojson"
    one = classify(*pair, tmp_path / "one", footprints_path=fp)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  memory_limit="2GB") as c, distributed.Client(c) as client:
        two = classify_distributed(*pair, tmp_path / "two", client, footprints_path=fp, block_cells=20,
                                   chunk_points=100_000)
    assert one["buildings"] == two["buildings"] > 10
    for name in ("buildings.csv", "buildings.geojson", "damage_map.html"):
        assert filecmp.cmp(tmp_path / "one" / name, tmp_path / "two" / name, shallow=False), name
    # the graded cloud: the post-event COPC file read in parts (a LAZ of variable-size chunks)
    x, y = laspy.read(tmp_path / "one" / "post_grades.laz"), laspy.read(tmp_path / "two" / "post_grades.laz")
    for dim in x.points.array.dtype.names:
        np.testing.assert_array_equal(x.points.array[dim], y.points.array[dim], err_msg=dim)


@pytest.mark.parametrize("geometry_only", [False, True])
@pytest.mark.parametrize("start,stop,chunk", [(0, None, 20_000), (1_000, 30_000, 7_000), (30_000, 30_001, 5),
                                              (50_000, None, 100_000), (13_000, 90_000, 3)])
def test_a_range_of_a_copc_file_reads_the_points_reading_it_whole_gives(box_copc, start, stop, chunk, geometry_only):
    """Parts of a file are streamed by point ranges; the LAZ backend's seek lands on other
    points in a file of variable-size chunks, so those ranges are read by the chunk table.
    A geometry-only read (the tiling's summaries of a COPC epoch) gives the same coordinates,
    classes and extra dimensions."""
    from quakescan.formats.pointcloud import read_point_range

    path, _ = box_copc
    whole = laspy.read(path)
    stop = whole.header.point_count if stop is None else stop
    with laspy.open(path) as reader:
        parts = list(read_point_range(reader, start, stop, chunk, geometry_only=geometry_only))
    for dim in ("X", "Y", "Z", "building_id"):
        got = np.concatenate([np.asarray(p.array[dim]) for p in parts])
        np.testing.assert_array_equal(got, np.asarray(whole.points.array[dim])[start:stop], err_msg=dim)
    np.testing.assert_array_equal(np.concatenate([np.asarray(p.classification) for p in parts]),
                                  np.asarray(whole.classification)[start:stop])


def test_a_geometry_read_decompresses_only_coordinates_class_and_extra_dimensions(box_copc):
    from quakescan.formats.copc import copc_index

    index = copc_index(box_copc[0])
    every, a = index.points_in_nodes(index.nodes[:5])
    some, b = index.points_in_nodes(index.nodes[:5], fields="geometry")
    np.testing.assert_array_equal(a, b)
    for dim in ("X", "Y", "Z", "classification", "building_id", "grade"):
        np.testing.assert_array_equal(every[dim], some[dim], err_msg=dim)
    assert not np.array_equal(every["gps_time"], some["gps_time"])  # left out: not the file's values


def test_a_range_of_a_copc_file_held_in_memory_is_read_from_its_start(box_copc):
    """No file to read chunks from (an in-memory stream): the points before the range are
    decompressed and dropped, the range is still the file's."""
    import io

    from quakescan.formats.pointcloud import read_point_range

    path, _ = box_copc
    whole = laspy.read(path)
    with laspy.open(io.BytesIO(path.read_bytes())) as reader:
        got = np.concatenate([np.asarray(p.array["X"]) for p in read_point_range(reader, 30_000, 90_000, 7_000)])
    np.testing.assert_array_equal(got, np.asarray(whole.points.array["X"])[30_000:90_000])
