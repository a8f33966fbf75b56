"""`experiment paper` as Dask tasks: the same clouds, levels of detection and numbers as one
process, and either run resumes the other's."""
import json

import pytest

from quakescan.cli import main

TINY = ["--buildings", "4", "--test-mix", "0:2,3:1,4:1,5:2", "--trees", "10", "--seed", "2"]


@pytest.mark.slow
def test_the_experiment_on_a_local_cluster_gives_the_single_process_numbers(tmp_path, capsys):
    here, dask = tmp_path / "here", tmp_path / "dask"
    assert main(["experiment", "paper", "-o", str(here), *TINY, "--threads", "1"]) == 0
    capsys.readouterr()
    assert main(["experiment", "paper", "-o", str(dask), *TINY, "--workers", "2", "--progress"]) == 0
    captured = capsys.readouterr()
    assert "Dask: a LocalCluster of 2 workers" in captured.out
    steps = 5 + (3 * 7 + 2) + 1 + 6 + 2  # as one process counts them
    assert f"experiment  {steps}/{steps}  100 %" in captured.err
    ours, theirs = (json.loads((d / "results.json").read_text()) for d in (here, dask))
    assert theirs["results"] == ours["results"]
    assert theirs["ablation"] == ours["ablation"]
    assert theirs["levels_of_detection"] == ours["levels_of_detection"]
    assert theirs["shipped_default"] == ours["shipped_default"]
    assert "as Dask tasks on 2 workers" in (dask / "README.md").read_text()
    clouds = sorted(p.name for p in (here / "data").glob("*.las"))
    assert len(clouds) == 3 * 7 + 2 and clouds == sorted(p.name for p in (dask / "data").glob("*.las"))
    for name in clouds:
        assert (dask / "data" / name).read_bytes() == (here / "data" / name).read_bytes(), name
    # the Dask run's caches are the single process's: resuming it acquires and describes nothing
    assert main(["experiment", "paper", "-o", str(dask), *TINY, "--threads", "1"]) == 0
    shown = capsys.readouterr().err
    assert ": DIM in" not in shown and ": ULS in" not in shown and " buildings in " not in shown
    assert json.loads((dask / "results.json").read_text())["results"] == ours["results"]


def test_experiment_workers_must_be_at_least_one(tmp_path, capsys):
    assert main(["experiment", "paper", "-o", str(tmp_path / "x"), "--workers", "0"]) == 2
    assert "--workers must be at least 1, got 0" in capsys.readouterr().err


def test_experiment_takes_workers_or_a_scheduler_not_both(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["experiment", "paper", "-o", str(tmp_path / "x"), "--workers", "2", "--scheduler", "tcp://h:1"])
    assert "not allowed with argument" in capsys.readouterr().err
