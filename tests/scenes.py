"""Scanned pre/post pairs of a small box city with known collapses, shared by the pipeline tests."""
from quakescan.acquisition.scan import scan
from quakescan.acquisition.survey import preset
from quakescan.formats.synthetic import box_city

UTM = (500000.0, 5000000.0, 0.0)
HEIGHTS = (9.0, 12.0, 9.0, 12.0, 9.0, 12.0)


def scan_box_pair(folder, post_heights, origin=UTM, seed_post=2) -> tuple:
    """Scan a 2×3 box city (HEIGHTS) and its post-event state (`post_heights`; a building whose
    height changed is grade 5) into folder/pre.las and folder/post.las; returns the grades."""
    s = preset("paper").replace(pulse_rate_hz=100_000.0)
    grades = tuple(5 if a != b else 0 for a, b in zip(HEIGHTS, post_heights))
    scan(box_city(rows=2, cols=3, height=HEIGHTS, origin=origin), s, folder / "pre.las", seed=1)
    scan(box_city(rows=2, cols=3, height=post_heights, origin=origin, epoch="post", grades=grades), s,
         folder / "post.las", seed=seed_post)
    return grades
