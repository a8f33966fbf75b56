"""The library's error classes: one base, a few kinds, each message naming the input."""


class QuakeScanError(Exception):
    """Base class; the CLI turns it into a message and exit status 2."""


class SceneError(QuakeScanError):
    """A scene bundle (scene.json + mesh.ply) is missing, malformed or inconsistent."""


class SurveyError(QuakeScanError):
    """A survey (flight plan + scanner) is invalid or does not cover the scene."""


class PointCloudError(QuakeScanError):
    """A point cloud file cannot be read or written as asked."""


class ResultsError(QuakeScanError):
    """A result file cannot be read or written."""


def read_json_file(path, what: str, error: type[QuakeScanError]):
    """The parsed JSON of `path`, or `error` saying "<path>: <what> does not exist" or
    "<path>: not valid JSON (...)"; every file-format reader of the library shares it."""
    import json
    from pathlib import Path

    path = Path(path)
    try:
        return json.loads(path.read_bytes())  # bytes: JSON detects its UTF encoding, not the locale
    except FileNotFoundError:
        raise error(f"{path}: {what} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise error(f"{path}: not valid JSON ({e})") from None
