"""The architecture's import rules, read from the source (ast): the add-on never imports the
library, the library never imports Blender, and neither package's modules import each other
in a circle, counting the imports inside functions."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _imports(path: Path, package: str, top_level_only: bool, root: Path = ROOT):
    """Absolute names of the modules `path` imports (relative ones resolved within `package`)."""
    tree = ast.parse(path.read_text(), str(path))
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    if top_level_only:  # imports under `if TYPE_CHECKING:`-free module-level statements only
        nodes = [n for n in nodes if isinstance(n, (ast.Import, ast.ImportFrom))]
    out = set()
    mod_parts = [package] + list(path.relative_to(root / package_dir(package)).with_suffix("").parts)
    if mod_parts[-1] == "__init__":
        mod_parts = mod_parts[:-1] + ["__init__"]
    for n in nodes:
        if isinstance(n, ast.Import):
            out.update(a.name for a in n.names)
        elif isinstance(n, ast.ImportFrom):
            if n.level:
                base = mod_parts[:-n.level]
                name = ".".join(base + ([n.module] if n.module else []))
                if n.module:
                    out.add(name)
                else:  # from . import x: x is a module of the package
                    out.update(f"{name}.{a.name}" for a in n.names)
            else:
                out.add(n.module)
    return out


def package_dir(package):
    return {"quakescan": "core", "quakescan_damage": "addon"}[package]


def _modules(package):
    folder = ROOT / package_dir(package)
    return {p: package + "." + ".".join(p.relative_to(folder).with_suffix("").parts) for p in folder.rglob("*.py")}


def test_the_add_on_never_imports_the_library():
    for path in _modules("quakescan_damage"):
        bad = {m for m in _imports(path, "quakescan_damage", False) if m and m.split(".")[0] in ("quakescan", "core")}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_the_library_never_imports_blender():
    for path in _modules("quakescan"):
        bad = {m for m in _imports(path, "quakescan", False) if m and m.split(".")[0] in ("bpy", "bmesh", "addon",
                                                                                           "quakescan_damage")}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


@pytest.mark.parametrize("package", ["quakescan", "quakescan_damage"])
def test_no_import_cycle_even_through_imports_inside_functions(package):
    """A module imported inside a function is loaded on use, but it is a dependency all the
    same: a circle of them is one room that cannot be understood, tested or moved alone."""
    mods = _modules(package)
    names = {name.removesuffix(".__init__") for name in mods.values()}
    graph = {}
    for path, name in mods.items():
        me = name.removesuffix(".__init__")
        deps = {d.removesuffix(".__init__") for d in _imports(path, package, False)}
        graph[me] = {d for d in deps if d in names and d not in (package, me)}
    state = {}

    def visit(n, stack):
        state[n] = "open"
        for d in sorted(graph.get(n, ())):
            if state.get(d) == "open":
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d, stack + [d])
        state[n] = "done"

    for n in sorted(graph):
        if n not in state:
            visit(n, [n])
    assert len(graph) > (40 if package == "quakescan" else 10)  # the walk saw the package


# The stages in the order data flows through them (docs/layout.md): a module may import only
# from its own stage and the ones before it, at module level and inside functions alike.
# results/ (the files a classification writes, the metrics that score it) reads no model, so
# it comes before learning/, whose training reports score with its metrics; the classify run
# (assessment/) is on top of both, its Dask engine (distributed/) above it.
STAGE_ORDER = ("errors", "grades", "runtime", "grid", "generator", "formats", "acquisition", "injection",
               "change", "results", "learning", "assessment", "distributed", "studies", "demo", "api", "cli")
# Upward imports that remain, each with its reason (none).
UPWARD_ALLOWED: set = set()


def _stage(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _upward_imports(modules: dict, root: Path) -> list[str]:
    """'a -> b' for every import of `modules` ({path: name}) that goes up STAGE_ORDER."""
    rank = {s: i for i, s in enumerate(STAGE_ORDER)}
    bad = []
    for path, name in modules.items():
        me = _stage(name)
        if me == "__init__":
            continue
        assert me in rank, f"{path}: stage {me!r} is not in STAGE_ORDER"
        for dep in _imports(path, "quakescan", False, root):
            if not dep or not dep.startswith("quakescan.") or _stage(dep) in ("__init__", "__version__"):
                continue
            if rank[_stage(dep)] > rank[me] and (me, _stage(dep)) not in UPWARD_ALLOWED:
                bad.append(f"{name} -> {dep}")
    return sorted(bad)


def test_every_stage_imports_only_from_the_stages_before_it():
    bad = _upward_imports(_modules("quakescan"), ROOT)
    assert not bad, "imports up the stages: " + ", ".join(bad)


def test_the_stage_rule_sees_an_upward_import_inside_a_function(tmp_path):
    (tmp_path / "core" / "formats").mkdir(parents=True)
    bad = tmp_path / "core" / "formats" / "bad.py"
    bad.write_text("def f():\n    from ..change import surface\n")
    fine = tmp_path / "core" / "formats" / "fine.py"
    fine.write_text("from ..grid.density import DENSITY_CELL_M\n")
    found = _upward_imports({bad: "quakescan.formats.bad", fine: "quakescan.formats.fine"}, tmp_path)
    assert found == ["quakescan.formats.bad -> quakescan.change"]  # `from ..change import x` names the package
