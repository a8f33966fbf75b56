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


def _import_cycle(mods: dict, package: str, root: Path = ROOT) -> str | None:
    """The first circle of imports among `mods` ({path: module name}), imports inside
    functions included, as 'a -> b -> a'; None when there is none."""
    names = {name.removesuffix(".__init__") for name in mods.values()}
    graph = {}
    for path, name in mods.items():
        me = name.removesuffix(".__init__")
        deps = {d.removesuffix(".__init__") for d in _imports(path, package, False, root)}
        graph[me] = {d for d in deps if d in names and d not in (package, me)}
    state: dict = {}

    def visit(n, stack):
        state[n] = "open"
        for d in sorted(graph.get(n, ())):
            if state.get(d) == "open":
                return " -> ".join(stack[stack.index(d):] + [d])
            if d not in state and (found := visit(d, stack + [d])):
                return found
        state[n] = "done"
        return None

    for n in sorted(graph):
        if n not in state and (found := visit(n, [n])):
            return found
    return None


@pytest.mark.parametrize("package", ["quakescan", "quakescan_damage"])
def test_no_import_cycle_even_through_imports_inside_functions(package):
    """A module imported inside a function is loaded on use, but it is a dependency all the
    same: a circle of them is one room that cannot be understood, tested or moved alone."""
    mods = _modules(package)
    cycle = _import_cycle(mods, package)
    assert cycle is None, "import cycle: " + str(cycle)
    assert len(mods) > (40 if package == "quakescan" else 10)  # the walk saw the package


def test_the_cycle_rule_sees_a_circle_closed_inside_a_function(tmp_path):
    (tmp_path / "core" / "change").mkdir(parents=True)
    a, b, c = (tmp_path / "core" / "change" / f"{n}.py" for n in "abc")
    a.write_text("from . import b\n")
    b.write_text("def f():\n    from .c import g\n")
    c.write_text("def g():\n    from .a import x\n")
    mods = {a: "quakescan.change.a", b: "quakescan.change.b", c: "quakescan.change.c"}
    assert _import_cycle(mods, "quakescan", tmp_path) == ("quakescan.change.a -> quakescan.change.b -> "
                                                          "quakescan.change.c -> quakescan.change.a")
    c.write_text("def g():\n    return 1\n")
    assert _import_cycle(mods, "quakescan", tmp_path) is None


def _private_imports(modules: dict, root: Path = ROOT) -> list[str]:
    """'a imports b._name' for every private name (one leading underscore) a module imports
    from a module of another package of the library: a package's private names are its own."""
    bad = []
    for path, name in modules.items():
        me = name.rsplit(".", 1)[0] if not name.endswith(".__init__") else name.removesuffix(".__init__")
        parts = name.split(".")
        tree = ast.parse(path.read_text(), str(path))
        for n in ast.walk(tree):
            if not isinstance(n, ast.ImportFrom):
                continue
            target = ".".join(parts[:-n.level] + ([n.module] if n.module else [])) if n.level else (n.module or "")
            if not target.startswith("quakescan"):
                continue
            for a in n.names:
                full = f"{target}.{a.name}"
                owner = full.rsplit(".", 1)[0]
                private = a.name.startswith("_") and not a.name.startswith("__")
                if private and owner.rsplit(".", 1)[0] != me and owner != me:
                    bad.append(f"{name} imports {full}")
    return sorted(bad)


def test_no_private_name_is_imported_across_packages():
    bad = _private_imports(_modules("quakescan"))
    assert not bad, ", ".join(bad)


def test_the_private_name_rule_sees_a_private_import_from_another_package(tmp_path):
    (tmp_path / "core" / "results").mkdir(parents=True)
    bad = tmp_path / "core" / "results" / "bad.py"
    bad.write_text("def f():\n    from ..formats.pointcloud import _crs_of\n")
    own = tmp_path / "core" / "results" / "own.py"
    own.write_text("from .writers import _rgb8\nfrom . import _kernels\n")
    found = _private_imports({bad: "quakescan.results.bad", own: "quakescan.results.own"}, tmp_path)
    assert found == ["quakescan.results.bad imports quakescan.formats.pointcloud._crs_of"]


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
