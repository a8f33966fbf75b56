"""The library's error classes: one base, a few kinds, each message naming the input."""


class QuakeScanError(Exception):
    """Base class; the CLI turns it into a message and exit status 2."""


class SceneError(QuakeScanError):
    """A scene bundle (scene.json + mesh.ply) is missing, malformed or inconsistent."""


class SurveyError(QuakeScanError):
    """A survey (flight plan + scanner) is invalid or does not cover the scene."""


class PointCloudError(QuakeScanError):
    """A point cloud file cannot be read or written as asked."""


class ClassifyError(QuakeScanError):
    """Classification cannot run as asked (its inputs do not make a pair it can grade)."""


class ResultsError(QuakeScanError):
    """A result file cannot be read or written."""


def input_file_problem(path, what: str) -> str | None:
    """Why `path` cannot be read as the input file `what` ("<path>: <what> does not exist",
    "... is a folder, not a file", "... is not a regular file (a device, FIFO or socket)"),
    or None when it is a regular file (or a link to one). A device such as /dev/zero never
    ends and a FIFO blocks until somebody writes to it: both are refused before a read."""
    import os
    import stat

    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return f"{path}: {what} does not exist"
    except OSError as e:  # permission, a name too long, a loop of links
        return f"{path}: {what} cannot be opened ({e.strerror or e})"
    if stat.S_ISDIR(mode):
        return f"{path}: {what} is a folder, not a file"
    if not stat.S_ISREG(mode):
        return f"{path}: {what} is not a regular file (a device, FIFO or socket); give a file"
    return None


def check_input_file(path, what: str, error: type[QuakeScanError]) -> None:
    """Raise `error` with `input_file_problem`'s reason when `path` is not a regular file."""
    problem = input_file_problem(path, what)
    if problem:
        raise error(problem)


def read_json_file(path, what: str, error: type[QuakeScanError]):
    """The parsed JSON of `path`, or `error` saying "<path>: <what> does not exist" (or is not
    a regular file, `input_file_problem`), "<path>: not valid JSON (...)" or that it is
    nested too deeply to read; every file-format reader of the library shares it."""
    import json
    from pathlib import Path

    path = Path(path)
    check_input_file(path, what, error)
    too_deep = error(f"{path}: {what} nests arrays or objects more than {MAX_JSON_DEPTH} levels deep; "
                     "no real file of this kind does (a broken or hostile file?)")
    try:
        doc = json.loads(path.read_bytes())  # bytes: JSON detects its UTF encoding, not the locale
    except FileNotFoundError:
        raise error(f"{path}: {what} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise error(f"{path}: not valid JSON ({e})") from None
    except RecursionError:  # the parser recurses once per [ or {
        raise too_deep from None
    if json_depth(doc) > MAX_JSON_DEPTH:  # every reader and writer after this one recurses too
        raise too_deep
    return doc


# The deepest JSON a reader accepts: a CityJSON solid's boundaries are 4 arrays deep, a
# GeoJSON multipolygon's coordinates 4, a feature's attributes rarely a handful; the code that
# walks a document recurses once a level, and Python stops at 1000.
MAX_JSON_DEPTH = 64


def json_depth(doc) -> int:
    """How many arrays and objects deep `doc` nests (a number or text: 0), without recursion."""
    deepest, stack = 0, [(doc, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, dict):
            value = list(value.values())
        elif not isinstance(value, list):
            continue
        deepest = max(deepest, depth)
        stack.extend((v, depth + 1) for v in value if isinstance(v, (dict, list)))
    return deepest
