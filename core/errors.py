"""The library's error classes: one base, a few kinds, each message naming the input."""


class QuakeScanError(Exception):
    """Base class; the CLI turns it into a message and exit status 2."""


class SceneError(QuakeScanError):
    """A scene bundle (scene.json + mesh.ply) is missing, malformed or inconsistent."""


class SurveyError(QuakeScanError):
    """A survey (flight plan + scanner) is invalid or does not cover the scene."""


class PointCloudError(QuakeScanError):
    """A point cloud file cannot be read or written as asked."""
