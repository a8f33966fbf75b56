"""`quakescan inject`: EMS-98 damage injected into a real point cloud."""
from __future__ import annotations

import argparse

from ..runtime.output_folder import exclusive_run
from .options import check_number, check_seed
from .reporting import echo


def _grade_mix(text: str) -> dict:
    from ..grades import parse_grade_counts

    try:  # the other buildings stay at 0: a mix counts the damaged ones
        return parse_grade_counts(text, allowed=(3, 4, 5))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def cmd_inject(args) -> int:
    from ..injection.inject import InjectionError, InjectSettings, inject
    from ..results.evaluation import read_grade_csv

    check_seed(args.seed)
    check_number("--min-points", args.min_points, 1, integer=True)
    check_number("--range-noise", args.range_noise, 0)
    grades = read_grade_csv(args.grades, InjectionError) if args.grades else None
    mix = args.grade_mix if grades is None else None
    if grades is None and mix is None:
        mix = dict(DEFAULT_MIX)
    settings = InjectSettings(seed=args.seed, grades=grades, grade_mix=mix, min_points=args.min_points,
                              damage=args.damage, kind=args.sensor, range_noise_m=args.range_noise,
                              id_field=args.id_field)
    with exclusive_run(args.output, "inject", InjectionError):  # one injection in the folder at a time
        r = inject(args.cloud, args.footprints, args.output, settings)
    damaged = {g: sum(1 for v in r.grades.values() if v == g) for g in (3, 4, 5)}
    state = "up to date, kept" if r.reused else "written"
    echo(f"{r.post}: {state}; {sum(damaged.values())} buildings damaged "
         f"({', '.join(f'{n} at grade {g}' for g, n in damaged.items())}), {r.counts['moved']:,} returns moved, "
         f"{r.counts['removed']:,} removed; truth in {r.truth}, record in {r.record}")
    return 0


# without --grades or --grade-mix: a few of each damage grade, as a quick look at a tile
DEFAULT_MIX = {3: 5, 4: 5, 5: 5}


def add_inject(sub) -> None:
    c = sub.add_parser("inject", help="inject EMS-98 damage into a real point cloud (a post-event cloud with known "
                       "grades)",
                       description="Damage the buildings of a real cloud with the add-on's catalogue patterns on "
                       "proxy blocks of their footprints and re-cast the cloud's own pulses against them: the post-"
                       "event cloud is the real one where the surface still stands. Writes OUT/post.las (post.laz "
                       "for a compressed input), OUT/truth.csv, OUT/inject.json and OUT/scenes/.")
    c.add_argument("cloud", help="real point cloud (LAS/LAZ): the surface before the event")
    c.add_argument("--footprints", required=True, help="building footprints (GeoJSON) in the cloud's coordinates")
    c.add_argument("-o", "--output", required=True, help="output folder")
    g = c.add_mutually_exclusive_group()
    g.add_argument("--grades", help="CSV building_id,grade: the grade of each listed building (others 0)")
    g.add_argument("--grade-mix", type=_grade_mix, default=None, metavar="GRADE:COUNT,...",
                   help="damage this many buildings at each grade, drawn by --seed among those with --min-points "
                   "points (default 3:5,4:5,5:5)")
    c.add_argument("--seed", type=int, default=0, help="random seed: which buildings, which patterns (default 0)")
    c.add_argument("--min-points", type=int, default=200,
                   help="--grade-mix: a building needs this many points to be drawn (default 200)")
    c.add_argument("--damage", choices=("patterns", "physics", "both"), default="patterns",
                   help="grades 4-5 by the catalogue's patterns (default), rigid-body collapse, or a seeded half each")
    c.add_argument("--sensor", choices=("auto", "lidar", "dim"), default="auto",
                   help="how the cloud was sampled: lidar re-casts each return along its pulse (trajectory from GPS "
                   "time and scan angle), dim casts from above at the cloud's spacing; auto: lidar when the file has "
                   "GPS times and scan angles (default)")
    c.add_argument("--range-noise", type=float, default=None, metavar="M",
                   help="range noise of new returns in metres (default: estimated from the cloud's ground returns)")
    c.add_argument("--id-field", default=None, help="footprint property holding the building ID (as classify's)")
    c.set_defaults(func=cmd_inject)
