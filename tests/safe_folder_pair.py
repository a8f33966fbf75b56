"""The small classified pair the output-folder tests share (tests/test_safe_folder_*.py)."""
import pytest

from quakescan.change.settings import PipelineSettings
from quakescan.learning.model import save_model
from quakescan.learning.training import TrainingPair, train
from tests.scenes import scan_box_pair

RESULTS = ["buildings.csv", "buildings.geojson", "buildings.qml", "damage_map.html", "damage_map.png",
           "post_grades.las", "summary.json"]


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """pre.las, post.las (buildings 2 and 4 collapsed) and model.skops, a 10-tree forest of the pair."""
    d = tmp_path_factory.mktemp("safe_folder_pair")
    scan_box_pair(d, (9.0, 4.0, 9.0, 3.0, 9.0, 12.0))
    model, _, _ = train([TrainingPair(str(d / "pre.las"), str(d / "post.las"))], PipelineSettings(),
                        n_estimators=10, test_size=0.0)
    save_model(model, d / "model.skops")
    return d


def names(folder):
    return sorted(p.name for p in folder.iterdir())
