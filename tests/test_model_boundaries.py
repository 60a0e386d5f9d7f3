"""The model's dependencies point one way: it does not depend on data preparation, and the
modules its decode is built from do not know ATGSModel (not even for type hints)."""

from __future__ import annotations

import ast

from test_packaging import REPO, import_graph


def _reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for nxt in graph[todo.pop()] - seen:
            seen.add(nxt)
            todo.append(nxt)
    return seen


def test_the_model_does_not_depend_on_data_preparation() -> None:
    graph = import_graph()
    assert "atgs.geometry.seen_space" in graph["atgs.model.anchor_setup"]
    for name in (m for m in graph if m.startswith("atgs.model.")):
        reached = sorted(m for m in _reachable(graph, name) if m.startswith("atgs.data"))
        assert not reached, f"{name} imports {reached}"


def test_rig_geometry_builds_on_nothing_above_it() -> None:
    """atgs.geometry serves data preparation, the model and training alike, so it imports none
    of them (nor the viewers, the exporters or the command lines)."""
    graph = import_graph()
    geometry = [m for m in graph if m.startswith("atgs.geometry.")]
    assert {"atgs.geometry.projection", "atgs.geometry.free_space", "atgs.geometry.coverage"} <= set(geometry)
    above = ("atgs.data", "atgs.model", "atgs.train", "atgs.eval", "atgs.viewer", "atgs.web", "atgs.cli", "atgs.export")
    for name in geometry:
        reached = sorted(m for m in _reachable(graph, name) if m.startswith(above))
        assert not reached, f"{name} imports {reached}"


def test_decode_parts_import_nothing_of_the_model_class() -> None:
    """Every import counts here, ``if TYPE_CHECKING:`` blocks included: the inference decode's
    gather and the shared steps are used by atgs_model, never the other way round."""
    for part in ("model/fast_decode", "model/decoder", "model/anchor_motion", "model/smoothing", "geometry/clearance"):
        tree = ast.parse((REPO / "atgs" / f"{part}.py").read_text())
        imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        assert "atgs.model.atgs_model" not in imported, part
