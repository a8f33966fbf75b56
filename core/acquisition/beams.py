"""From pulses to points: how the scanner's rays become returns, noisy ranges, intensities
and packed LAS records, one batch of pulses at a time (`Simulator.run_batch`, run on the
worker threads of `quakescan.acquisition.scan`; the loops it runs, compiled (`_scan_kernels`) or their
numpy references (`_scan_reference`), are chosen once by the scan and handed to the `Simulator`).

Numerics: rays are cast by `quakescan.acquisition.raycast.RayCaster` (local origin, float32 only at the
Embree boundary, hits refined in float64), so a scene at UTM coordinates gives the same
points as the same scene at the origin.

Beam model (`Survey.beam`):
- `single`: one ray per pulse, one return at the exact hit (default, fastest).
- `full`: every pulse casts `Survey.sub_rays` rays over its footprint (rings out to the
  1/e² divergence, Gaussian weights); sub-ray hits are grouped by range into returns
  (a new return where the range gap exceeds `echo_separation_m`); a return's range is the
  energy-weighted mean of its sub-rays, its position lies on the central ray at that
  range, its labels come from its strongest sub-ray, and returns weaker than
  `min_echo_energy` of the pulse are not detected.
- `adaptive`: the central ray of every pulse first; a pulse gets the full beam only when
  a neighbouring pulse whose footprint could overlap its own (in its scan line and in
  the neighbouring lines, as far as the footprint reaches) misses where it hits (or the
  reverse) or hits a point farther than `adaptive_edge_m` from the plane of its own
  hit: a depth discontinuity or a crease.
  Elsewhere the footprint lies on one plane and the full beam would return the central
  hit within a fraction of a millimetre (measured in bench/bench_scan.py).
  Discontinuities narrower than the pulse spacing (wires, antennas) can be missed.

Vegetation (`quakescan.acquisition.vegetation`): a ray that hits a porous face (a tree crown) is returned
there with probability 1 - transmission, else cast again from just beyond the hit; every
beam model's rays do this, seeded per (seed, line, pulse, sub-ray, crossing). Re-cast rays
are not counted in `rays_cast`. A scene without porous faces draws no transmission: its rays
stop at their first hit, so its clouds do not depend on this model.

Strip misalignment (`Survey.strip_misalignment_m`, default 0): every point of flight line k
is moved by one 3-D offset `strip_offset(survey, seed, k)`, added where the final float64
point is formed (local hit + the line's shift to LAS coordinates), in the compiled and the
numpy paths alike. Rays are cast without it: it is a registration error of the processed
strip, not a different flight.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import PointCloudError
from ..formats.pointcloud import SCALE, PointChunk
from .pulses import Batch, Pulses, pulse_count
from ._scan_reference import loops as choose_loops
from .raycast import RayCaster
from .survey import FlightLine, Survey


class Simulator:
    def __init__(self, caster: RayCaster, survey: Survey, seed: int, shift=None, header=None, loops=None):
        """`shift` turns local coordinates into LAS-offset coordinates; with a LAS `header`
        batches come back as packed records; `loops`: the module whose loops it runs
        (`_scan_reference.loops`; default the compiled ones)."""
        self.caster = caster
        self.survey = survey
        self.seed = seed
        self.shift = np.asarray(caster.local_origin if shift is None else shift, dtype=np.float64)
        self.header = header
        self.loops = choose_loops(True) if loops is None else loops
        # The compiled loops also fuse the single-ray path into one pass (the references form
        # the same points step by step).
        self.fused = hasattr(self.loops, "refine_and_pack")
        # neighbour at the same angle in the next scan line, counted in in-FOV pulses
        self.ppl = max(1, int(round(survey.pulses_per_line * survey.fov_fraction)))
        self.ppl_raw = max(1, int(round(survey.pulses_per_line)))
        # Adaptive mode compares a pulse with every pulse whose footprint could overlap its own:
        # in the scan line the footprint spans half_div / angle_step pulses (angles, exact);
        # across lines it spans the footprint radius at the longest slant range / line spacing.
        half_div = survey.beam_divergence_mrad * 1e-3 / 2
        slant = (survey.altitude_agl_m + caster.bounds_local[1, 2] - caster.bounds_local[0, 2]) / math.cos(
            math.radians(survey.fov_deg / 2))
        k_in = max(1, math.ceil(half_div / survey.angle_step_rad))
        k_lines = max(1, math.ceil(slant * half_div / (survey.speed_m_s / survey.scan_rate_hz)))
        self.neighbour_offsets = sorted({m * self.ppl + l for m in range(0, k_lines + 1)
                                         for l in range(-k_in, k_in + 1) if m * self.ppl + l > 0})
        self.halo_raw = k_lines * self.ppl_raw + k_in + 1
        pad = 0.01
        self.box = caster.bounds_local + np.array([[-pad] * 3, [pad] * 3])
        self._sub_ray_pattern()

    def _sub_ray_pattern(self):
        s = self.survey
        half = s.beam_divergence_mrad * 1e-3 / 2
        offsets, weights = [(0.0, 0.0)], [1.0]
        for k in range(1, s.beam_rings + 1):
            alpha = half * k / s.beam_rings
            m = 6 * k
            for i in range(m):
                phi = 2 * math.pi * (i + 0.5 * (k % 2)) / m
                offsets.append((math.tan(alpha) * math.cos(phi), math.tan(alpha) * math.sin(phi)))
                # Gaussian beam: intensity exp(-2 r²/w²), w = 1/e² radius
                weights.append(math.exp(-2.0 * (alpha / half) ** 2) if half > 0 else 1.0)
        self.sub_offsets = np.array(offsets)
        w = np.array(weights)
        self.sub_weights = w / w.sum()

    def record_from_bytes(self, raw: bytes):
        """A packed LAS record from the bytes of one (`quakescan.acquisition.scan_checkpoint`)."""
        import laspy

        h = self.header
        a = np.frombuffer(bytearray(raw), dtype=h.point_format.dtype())
        return laspy.ScaleAwarePointRecord(a, h.point_format, h.scales, h.offsets)

    def pulses(self, line: FlightLine, j0: int, j1: int) -> Pulses:
        return Pulses(self.survey, line, j0, j1, self.caster.local_origin, self.box, self.loops)

    # --- one batch -------------------------------------------------------------------
    def run_batch(self, batch: Batch):
        """Simulate one batch. Returns (packed LAS record or PointChunk, stats)."""
        s = self.survey
        pulses = self.pulses(batch.line, batch.j0, batch.j1)
        stats = {"pulses_swept": batch.j1 - batch.j0, "pulses_emitted": pulses.n_fov, "pulses_cast": len(pulses),
                 "rays_cast": 0, "pulses_with_sub_rays": 0}
        shift = self.line_shift(batch.line.index)
        if s.beam == "single" and self.fused and self.header is not None:
            return self._single_fused(batch, pulses, shift, stats)
        o, d, o32, d32 = pulses.rays()
        # Every output point: a ray (row of o/d: the pulse's central ray) and a pulse index.
        if s.beam == "single":
            face, t = self.caster.cast(o, d, s.max_range_m, o32, d32, self.loops,
                                       self.ray_ids(batch.line, pulses.j))
            stats["rays_cast"] = len(pulses)
            ray = np.flatnonzero(face >= 0)
            face, rng_m = face[ray], t[ray]
            ret = nret = np.ones(len(ray), np.uint8)
        elif s.beam == "full":
            ray, face, rng_m, ret, nret = self._full_beam(o, d, pulses.plane_normal, stats,
                                                          ids=(batch.line, pulses.j))
        else:
            ray, face, rng_m, ret, nret = self._adaptive(batch, pulses, o, d, o32, d32, stats)
        pulse = ray  # rays are the batch's pulses, in order
        # Noise drawn per batch from (seed, line, batch): reproducible whatever the threads.
        # Standard normal noise in float32 (plenty for centimetre noise, half the cost), drawn
        # per batch from (seed, line, batch): reproducible whatever the number of threads.
        rng = np.random.default_rng([self.seed, batch.line.index, batch.number])
        noise = (rng.standard_normal(len(ray), dtype=np.float32) if s.range_noise_sigma_m > 0
                 else np.zeros(len(ray), np.float32))
        stats["points"] = len(ray)
        out = self._output(pulses, batch.line.index, ray, pulse, face, rng_m, noise, ret, nret, o, d, shift, stats)
        return out, stats

    def ray_ids(self, line: FlightLine, j: np.ndarray, k: int = 1):
        """Identities of rays for the transmission draws of porous faces (None when the scene
        has none: nothing is drawn)."""
        if self.caster.face_porous is None:
            return None
        from .vegetation import RayIds

        return RayIds(self.seed, line.index, j, k)

    def line_shift(self, line_index: int) -> np.ndarray:
        """Local → LAS-offset coordinates for the points of one flight line: `shift` plus the
        line's strip misalignment (`shift` itself, untouched, when there is none)."""
        if self.survey.strip_misalignment_m == 0:
            return self.shift
        return self.shift + strip_offset(self.survey, self.seed, line_index)

    def _single_fused(self, batch: Batch, pulses: Pulses, shift: np.ndarray, stats):
        """The single-ray beam with the compiled loops: float32 rays → Embree → one pass that
        refines, adds noise and packs (same bytes as the general path, fewer passes)."""

        s, c, h, loop = self.survey, self.caster, self.header, self.loops
        ln = batch.line
        o32, d32, cs = loop.pulse_rays32(pulses.t, pulses.theta, ln.t_start, pulses.start_local, pulses.velocity,
                                    pulses.down, pulses.right)
        face = c.embree_faces(o32, d32, s.max_range_m)
        if c.face_porous is not None:
            from .vegetation import pass_porous

            def rays_of(idx):  # float64 rays of the few pulses that hit a crown, as refine_and_pack forms them
                return loop.pulse_rays(pulses.t[idx], pulses.theta[idx], ln.t_start, pulses.start_local, pulses.velocity,
                                  pulses.down, pulses.right)[:2]
            face = pass_porous(c, rays_of, None, face, float(s.max_range_m), self.ray_ids(ln, pulses.j))
        stats["rays_cast"] = len(pulses)
        hits = int(np.count_nonzero(face >= 0))
        rng = np.random.default_rng([self.seed, ln.index, batch.number])
        noise = (rng.standard_normal(hits, dtype=np.float32) if s.range_noise_sigma_m > 0
                 else np.zeros(hits, np.float32))
        a = np.empty(hits, dtype=h.point_format.dtype())
        m, ok, mins, maxs, by_return, by_face = loop.refine_and_pack(
            face, pulses.t, cs, ln.t_start, pulses.start_local, pulses.velocity, pulses.down, pulses.right,
            c.normals, c.plane_d, float(s.max_range_m), noise, s.range_noise_sigma_m, shift, SCALE,
            pulses.theta, pulses.forward, pulses.edge, np.uint16(ln.index + 1),
            c.face_building, c.face_grade, c.face_surface, c.face_class, c.face_reflectance,
            s.intensity_reference_range_m ** 2, _las_columns(a))
        stats["points"] = m
        return _kernel_record(h, a[:m], ok, mins, maxs, by_return, by_face, stats), stats

    def _output(self, pulses, line_index, ray, pulse, face, rng_m, noise, ret, nret, o, d, shift, stats):
        """Points → a packed LAS record (when the simulator has a header) or a PointChunk;
        fills stats with counts by return and by face, and the record's bounds. A point is
        o + d · (range + noise) + shift, `shift` being the line's (see `line_shift`)."""
        from .reflectance import intensity

        c, sigma = self.caster, self.survey.range_noise_sigma_m
        n_faces = len(c.face_surface)
        if self.header is not None and self.fused:
            h = self.header
            # np.empty, not zeros: the kernel writes every byte of every point
            a = np.empty(len(ray), dtype=h.point_format.dtype())
            ok, mins, maxs, by_return, by_face = self.loops.pack_points(
                ray, pulse, face, rng_m, noise, sigma, ret.astype(np.uint8), nret.astype(np.uint8), o, d,
                shift, SCALE, pulses.t, pulses.theta, pulses.forward, pulses.edge, np.uint16(line_index + 1),
                c.face_building, c.face_grade, c.face_surface, c.face_class, c.normals, c.face_reflectance,
                self.survey.intensity_reference_range_m ** 2, _las_columns(a))
            return _kernel_record(h, a, ok, mins, maxs, by_return, by_face, stats)
        stats["by_return"] = np.bincount(ret, minlength=16)[:16]
        stats["by_face"] = np.bincount(face, minlength=n_faces)
        chunk = PointChunk(
            xyz=o[ray] + d[ray] * (rng_m + sigma * noise.astype(np.float64))[:, None] + shift,
            gps_time=pulses.t[pulse],
            scan_angle_deg=np.degrees(pulses.theta[pulse]),
            return_number=ret, number_of_returns=nret,
            classification=c.face_class[face], building_id=c.face_building[face],
            grade=c.face_grade[face], surface=c.face_surface[face],
            point_source_id=np.full(len(ray), line_index + 1, np.uint16),
            scan_direction=pulses.forward[pulse],
            edge_of_flight_line=pulses.edge[pulse],
            intensity=intensity(c.face_reflectance[face], c.normals[face], d[ray], rng_m,
                                self.survey.intensity_reference_range_m),
        )
        if self.header is None:
            return chunk
        from ..formats.pointcloud import pack_points, record_bounds

        rec = pack_points(self.header, chunk)
        if rec is not None:
            stats["las_bounds"] = record_bounds(rec)
        return rec

    def _adaptive(self, batch: Batch, pulses: Pulses, o, d, o32, d32, stats):
        """Returns (ray, face, range, return, returns) like the other beam models, with
        `ray` indexing the rows of o/d (the batch's pulses)."""
        s, line = self.survey, batch.line
        n_line = pulse_count(s, line)
        # Central rays of the batch plus a halo of scan lines on each side, so that the
        # across-line neighbours of the batch's first and last scan lines are known.
        # Neighbours are counted in pulses inside the FOV (`rank`).
        before = self.pulses(line, max(0, batch.j0 - self.halo_raw), batch.j0)
        after = self.pulses(line, batch.j1, min(n_line, batch.j1 + self.halo_raw))
        n_ext = before.n_fov + pulses.n_fov + after.n_fov
        segments = []
        for part, offset, rays in ((before, 0, None), (pulses, before.n_fov, (o, d, o32, d32)),
                                   (after, before.n_fov + pulses.n_fov, None)):
            if rays is None:
                rays = part.rays()
            f_, t_ = self.caster.cast(rays[0], rays[1], s.max_range_m, rays[2], rays[3], self.loops,
                                      self.ray_ids(line, part.j))
            stats["rays_cast"] += len(part)
            segments.append((offset + part.rank, rays[0], rays[1], np.where(f_ >= 0, t_, 0.0), f_))
        offsets = np.array(self.neighbour_offsets, np.int64)
        flag = self.loops.flag_discontinuities_rows(n_ext, tuple(segments), offsets, self.caster.normals,
                                                    s.adaptive_edge_m)[1]
        face, t = segments[1][4], np.where(segments[1][4] >= 0, segments[1][3], np.inf)
        flagged = np.flatnonzero(flag)
        stats["pulses_with_sub_rays"] += len(flagged)
        plain = np.flatnonzero(~flag & (face >= 0))
        f_ray, f_face, f_rng, f_ret, f_nret = self._full_beam(o[flagged], d[flagged], pulses.plane_normal, stats,
                                                              count=False, ids=(line, pulses.j[flagged]))
        ray = np.concatenate([plain, flagged[f_ray]])
        order = np.argsort(ray, kind="stable")  # back to scan order
        ones = np.ones(len(plain), np.uint8)
        return (ray[order], np.concatenate([face[plain], f_face])[order],
                np.concatenate([t[plain], f_rng])[order], np.concatenate([ones, f_ret])[order],
                np.concatenate([ones, f_nret])[order])

    def _full_beam(self, origins, dirs, plane_normal, stats, count=True, ids=None):
        """Sub-rays over the footprints of the given pulses; returns formed per pulse.
        `ids` = (flight line, pulse index j per given pulse) for the crowns' transmission draws.

        Returns (pulse, face, range, return_number, number_of_returns) per detected return,
        pulse-major and return-minor (scan order); `pulse` indexes the given rays."""
        s = self.survey
        n, k = len(dirs), len(self.sub_weights)
        if n == 0:
            return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.uint8),
                    np.zeros(0, np.uint8))
        loop = self.loops
        sub = loop.sub_rays(dirs, plane_normal, self.sub_offsets)
        org = np.repeat(origins, k, axis=0)
        face, t = self.caster.cast(org, sub, s.max_range_m, loops=loop,
                                   ray_ids=self.ray_ids(ids[0], ids[1], k) if ids is not None else None)
        stats["rays_cast"] += n * k
        if count:
            stats["pulses_with_sub_rays"] += n
        face, t = face.reshape(n, k), t.reshape(n, k)
        return loop.form_returns(t, face, self.sub_weights, s.echo_separation_m, s.min_echo_energy, s.max_returns)


# Spawn key of the strip-misalignment stream: keeps it apart from the range-noise stream,
# whose entropy (seed, line, batch) could otherwise equal (seed, line) padded with zeros.
_STRIP_STREAM = 1


def strip_offset(survey: Survey, seed: int, line_index: int) -> np.ndarray:
    """The (3,) float64 offset added to every point of flight line `line_index`: Gaussian,
    `survey.strip_misalignment_m` per axis, drawn from (seed, line) alone, so the same seed
    gives the same offsets whatever the threads and batches (zeros without misalignment).

    It models what multi-strip ULS/ALS shows after trajectory processing: each strip slightly
    shifted against its neighbours by residual GNSS/INS and boresight errors."""
    sigma = survey.strip_misalignment_m
    if sigma == 0:
        return np.zeros(3)
    ss = np.random.SeedSequence([seed, line_index], spawn_key=(_STRIP_STREAM,))
    return sigma * np.random.default_rng(ss).standard_normal(3)


def _las_columns(a: np.ndarray) -> tuple:
    """The 14 columns of a format-6 QuakeScan record, in `_scan_kernels._write_point`'s order."""
    return tuple(a[n] for n in ("X", "Y", "Z", "intensity", "gps_time", "scan_angle", "bit_fields",
                                "classification_flags", "classification", "user_data", "point_source_id",
                                "building_id", "grade", "surface"))


def _kernel_record(header, a, ok, mins, maxs, by_return, by_face, stats):
    """A kernel's packed rows → a laspy record (None when empty); counts and bounds into stats."""
    import laspy

    if not ok:
        raise PointCloudError("point coordinates lie more than 2 147 km from the LAS offset")
    stats["by_return"], stats["by_face"] = by_return, by_face
    if len(a) == 0:
        return None
    offsets = np.asarray(header.offsets)
    stats["las_bounds"] = (mins * SCALE + offsets, maxs * SCALE + offsets, by_return[1:16])
    return laspy.ScaleAwarePointRecord(a, header.point_format, header.scales, header.offsets)
