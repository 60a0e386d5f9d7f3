"""Package boundaries: no import cycle anywhere in atgs (atgs.viewer and atgs.shaders included),
nothing imports a bare ``viewer`` or ``shaders``, every package lives under atgs/ with no
package-dir mapping or search-path hack, and pyproject.toml installs every package."""

from __future__ import annotations

import ast
try:
    import tomllib
except ImportError:  # Python 3.10: the same parser from PyPI (a test extra)
    import tomli as tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ROOTS = {"atgs": REPO / "atgs"}  # package name -> folder: everything lives under atgs/


def _modules() -> dict[str, Path]:
    out = {}
    for pkg, folder in ROOTS.items():
        for path in folder.rglob("*.py"):
            rel = path.relative_to(folder).with_suffix("").parts
            if rel[-1] == "__init__":
                rel = rel[:-1]
            out[".".join((pkg, *rel))] = path
    return out


def _runtime_imports(tree: ast.AST) -> list[tuple[str, list[str], int]]:
    """(module, imported names, level) of every import outside ``if TYPE_CHECKING:`` blocks,
    at any depth (an import inside a function is still a dependency)."""
    found = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.extend((a.name, [], 0) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            found.append((node.module or "", [a.name for a in node.names], node.level))
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports (``from pkg import sub`` counts as ``pkg.sub``
    when ``sub`` is a module; importing a module does not count as importing its parents)."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for module, names, level in _runtime_imports(ast.parse(path.read_text(), str(path))):
            if level:
                base = name.split(".") if is_pkg else name.split(".")[:-1]
                module = ".".join(base[: len(base) - level + 1] + ([module] if module else []))
            targets = [f"{module}.{n}" for n in names if f"{module}.{n}" in mods] or [module]
            graph[name].update(t for t in targets if t in mods and t != name)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}  # 1 = on the current path, 2 = done
    stack: list[str] = []

    def dfs(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = dfs(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = dfs(node)
            if found:
                return found
    return None


def test_cycle_finder_finds_cycles() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_package_import_graph_has_no_cycle() -> None:
    graph = import_graph()
    assert "atgs.viewer.cli" in graph and "atgs.viewer.app" in graph["atgs.viewer.cli"]
    assert "atgs.timeline" in graph["atgs.model.atgs_model"]
    cycle = find_cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test_nothing_imports_the_bare_viewer_or_shaders_folders() -> None:
    """The player is atgs.viewer; no folder of the repository root is a package of its own."""
    assert not (REPO / "viewer").exists() and not (REPO / "shaders").exists()
    offenders = []
    for folder in (REPO / "atgs", REPO / "bench", REPO / "tests"):
        for path in folder.rglob("*.py"):
            for module, _, level in _runtime_imports(ast.parse(path.read_text(), str(path))):
                if level == 0 and module.split(".")[0] in ("viewer", "shaders"):
                    offenders.append(f"{path.relative_to(REPO)}: {module}")
    assert not offenders, offenders


def test_pyproject_installs_every_package_under_atgs() -> None:
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "package-dir" not in cfg  # every package sits where its name says
    assert "__path__" not in (REPO / "atgs" / "__init__.py").read_text()
    on_disk = {name for name, path in _modules().items() if path.name == "__init__.py"}
    assert set(cfg["packages"]) == on_disk
    assert all(p == "atgs" or p.startswith("atgs.") for p in cfg["packages"])
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert all(target.startswith("atgs.") for target in scripts.values())


def test_shaders_are_found_through_the_atgs_namespace() -> None:
    from importlib.resources import files

    import atgs.viewer.splat_renderer as sr

    stages = (".vert", ".frag", ".geom", ".comp")
    names = sorted(p.name for p in files("atgs.shaders").iterdir() if p.name.endswith(stages))
    assert names == sorted(p.name for p in (REPO / "atgs" / "shaders").glob("*.*") if p.suffix in stages)
    assert Path(sr.__file__).resolve().parent == REPO / "atgs" / "viewer"


def test_the_wheel_ships_the_shaders_and_the_web_player(tmp_path) -> None:
    """pip install ships every file the desktop and web players read at run time (package data).
    Built from a copy of the tree: a build in the tree leaves build/ behind, whose stale copies
    of the package would hide a missing package-data glob from the next build."""
    import shutil
    import subprocess
    import sys
    import zipfile

    src = tmp_path / "src"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(".git", ".venv", "build", "*.egg-info", "__pycache__",
                                                             ".pytest_cache", "runs", "outputs", ".whl", ".gpu", ".gl"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", str(src),
                    "-w", str(tmp_path)], check=True, capture_output=True)
    (wheel,) = tmp_path.glob("atgs-*.whl")
    shipped = set(zipfile.ZipFile(wheel).namelist())
    needed = [p for folder in ("atgs/web/player", "atgs/shaders") for p in (REPO / folder).iterdir()
              if p.is_file() and p.suffix in (".js", ".html", ".css", ".vert", ".frag", ".geom", ".comp")]
    assert len(needed) > 10
    missing = [str(p.relative_to(REPO)) for p in needed if str(p.relative_to(REPO)) not in shipped]
    assert not missing
