"""What an install holds: the import name `quakescan` (never a top-level `core`, which other
projects use too), the add-on as `quakescan_damage`, and a wheel that runs `quakescan demo`
on its own: library, add-on and scene generator inside."""
import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# What the build reads; copied so the wheel never picks up a stale build/ of the checkout
# (setuptools packs whatever its build folder holds).
SOURCES = ("pyproject.toml", "README.md", "core", "addon", "blender_scripts")


def _run(cmd, cwd, **kw):
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True, **kw)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} exited {proc.returncode}:\n{proc.stderr[-3000:]}"
    return proc.stdout


INSTALLED = """
import importlib.metadata as m, importlib.util as u, json
print(json.dumps({
    "tops": sorted(n for n, d in m.packages_distributions().items() if "quakescan" in d),
    "core_files": [str(f) for f in m.files("quakescan") if f.parts[0] == "core"],
    "script": [e.value for e in m.entry_points(group="console_scripts", name="quakescan")],
    "found": {n: u.find_spec(n) is not None for n in ("quakescan", "quakescan_damage", "core")}}))
"""


def test_the_distribution_installs_quakescan_and_its_add_on_never_core(tmp_path):
    # asked outside the checkout, whose core/ folder and quakescan.egg-info a process started
    # in its root would see first
    got = json.loads(_run([sys.executable, "-c", INSTALLED], cwd=tmp_path))
    assert got["tops"] == ["quakescan", "quakescan_damage"] and got["core_files"] == []
    assert got["script"] == ["quakescan.cli:main"]
    assert got["found"] == {"quakescan": True, "quakescan_damage": True, "core": False}


def test_every_package_of_the_checkout_is_in_the_distribution():
    """setuptools takes only the packages listed: one left out is missing from every wheel
    (quakescan.studies.robustness was, and `quakescan robustness` failed installed)."""
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    dirs = {name: ROOT / folder for name, folder in config["package-dir"].items()}
    listed = set(config["packages"])
    for top in ("quakescan", "quakescan_damage"):
        for init in sorted(dirs[top].rglob("__init__.py")):
            name = ".".join([top, *init.parent.relative_to(dirs[top]).parts])
            assert name in listed, f"{init.parent.relative_to(ROOT)} ({name}) is not in pyproject.toml's packages"


@pytest.mark.slow
def test_the_wheel_installs_into_a_fresh_venv_and_runs_the_demo(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(ROOT / name, src / name)
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", tmp_path / "dist",
          src], cwd=tmp_path)
    (wheel,) = (tmp_path / "dist").glob("quakescan-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for member in ("quakescan/cli/__init__.py", "quakescan/acquisition/scan.py", "quakescan/data/default_model.skops", "quakescan/web/leaflet.js",
                   "quakescan/blender_scripts/generate_scenes.py", "quakescan_damage/__init__.py",
                   "quakescan_damage/geometry/shell.py", "quakescan_damage/blender_manifest.toml"):
        assert member in names, member
    assert not any(n.startswith("core/") or n.startswith("addon/") for n in names)

    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=tmp_path)
    py = venv / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", py, "install", "-q", "--no-deps", "--no-index", wheel],
         cwd=tmp_path)
    site = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=tmp_path).strip())
    # The dependencies from this environment, without downloading them: a .pth line only puts
    # the folder on sys.path (its own .pth files, among them the editable finder of this
    # checkout, are not run), after the fresh venv's own site-packages. Written after pip
    # ran, so pip never sees this environment's quakescan.
    deps = Path(_run([sys.executable, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                     cwd=tmp_path).strip())
    (site / "quakescan_dependencies.pth").write_text(f"{deps}\n")

    got = json.loads(_run([py, "-c", INSTALLED], cwd=tmp_path))
    assert got["tops"] == ["quakescan", "quakescan_damage"] and got["core_files"] == []
    assert got["found"] == {"quakescan": True, "quakescan_damage": True, "core": False}
    probe = ("import json, sys, quakescan, quakescan_damage; print(json.dumps([quakescan.__file__, "
             "quakescan_damage.__file__, [m for m in sys.modules if 'editable' in m]]))")
    lib, addon, editable = json.loads(_run([py, "-c", probe], cwd=tmp_path))
    assert Path(lib).is_relative_to(site) and Path(addon).is_relative_to(site) and editable == []

    out = tmp_path / "demo"
    _run([venv / "bin" / "quakescan", "demo", "-o", out, "--buildings", "4", "--seed", "2", "-q"], cwd=tmp_path)
    for name in ("buildings.csv", "damage_map.html", "evaluation.json", "summary.json"):
        assert (out / "result" / name).is_file(), name
    scene = json.loads((out / "city" / "post" / "scene.json").read_text())
    assert len(scene["buildings"]) == 4 and scene["crs"] == "EPSG:32633"

    blender = shutil.which("blender")
    if blender:  # Blender's own Python (Debian's 3.4: Python 3.10) runs the installed generator too
        _run([blender, "-b", "--factory-startup", "--python-exit-code", "1", "-P",
              site / "quakescan" / "blender_scripts" / "generate_scenes.py", "--", "--set", "generic",
              "--dataset", "mixed", "--buildings", "2", "--seed", "1", "--out", tmp_path / "by_blender"],
             cwd=tmp_path)
        assert (tmp_path / "by_blender" / "post" / "scene.json").is_file()
