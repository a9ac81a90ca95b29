"""The package's layers (docs/ARCHITECTURE.md) as a test: no import circle between modules, and every import points down.

Imports are read from the source with `ast`. The layer rules count every import: module level, inside functions (a
lazy import is still an arrow) and under TYPE_CHECKING. Circles count every import that runs, lazy ones included (a
function-level import that closes a loop hides a circle, it does not remove it), but not those under TYPE_CHECKING,
which never run. A failure names the module, what it imports and the rule it breaks.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import roadgrip

PACKAGE_DIR = Path(roadgrip.__file__).parent

# Top-level packages from the bottom up; each may import only those at its own rank or below. Within a rank, modules
# of different packages may import each other as long as no module-level circle forms (checked separately).
TOP_LEVEL_RANKS = (
    {"units", "validation"},
    {"vehicle"},
    {"data"},
    {"sim", "features", "models"},
    {"training", "estimators"},
    {"cloud"},
    {"fleet", "edge"},
    {"evaluation"},
    {"bench"},
    {"cli", "__main__"},
)

# Inside roadgrip.cloud, from the bottom up (the same rule).
CLOUD_RANKS = (
    {"domain"},
    {"formats"},
    {"settings", "metrics", "process", "localhost"},
    {"storage", "transport"},
    {"pipeline"},
    {"ingest"},
    {"api"},
    {"serve", "cluster"},
)
# The two assemblies share a rank but never import each other.
CLOUD_APART = ({"serve", "cluster"},)


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PACKAGE_DIR.rglob("*.py")}


def _running_nodes(tree: ast.AST):
    """Every node of the tree except what lies under `if TYPE_CHECKING:` (its else branch runs and is kept)."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.orelse:
                yield child
                yield from _running_nodes(child)
            continue
        yield node
        yield from _running_nodes(node)


def _imports(name: str, path: Path, known: set[str], running_only: bool = False) -> set[str]:
    """The roadgrip modules `name` imports (a `from package import module` counts as the module)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    tree = ast.parse(path.read_text(), str(path))
    for node in _running_nodes(tree) if running_only else ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("roadgrip"))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("roadgrip"):
                continue
            for alias in node.names:
                candidate = f"{target}.{alias.name}"
                found.add(candidate if candidate in known else target)
    return {m for m in found if m in known and m != name}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imports(name, path, known) for name, path in modules.items()}


@pytest.fixture(scope="module")
def running_graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imports(name, path, known, running_only=True) for name, path in modules.items()}


def _rank(name: str, ranks: tuple[set[str], ...], depth: int) -> int | None:
    parts = name.split(".")
    if len(parts) <= depth:
        return None
    key = parts[depth]
    for i, members in enumerate(ranks):
        if key in members:
            return i
    return None


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_every_module_is_ranked(graph):
    """A new top-level package or cloud folder must be given its place in the layers before it is used."""
    unranked = [m for m in graph if m != "roadgrip" and _rank(m, TOP_LEVEL_RANKS, 1) is None]
    unranked += [m for m in graph if m.startswith("roadgrip.cloud.") and _rank(m, CLOUD_RANKS, 2) is None]
    assert not unranked, (
        f"modules outside every layer (add them to tests/test_layers.py and ARCHITECTURE.md): {unranked}"
    )


def test_no_import_circle(running_graph):
    assert _cycles(running_graph) == []


@pytest.mark.parametrize(
    ("ranks", "depth", "scope"),
    [(TOP_LEVEL_RANKS, 1, "roadgrip."), (CLOUD_RANKS, 2, "roadgrip.cloud.")],
    ids=["package", "cloud"],
)
def test_imports_point_down(graph, ranks, depth, scope):
    upward = []
    for name, targets in graph.items():
        if not name.startswith(scope):
            continue
        own = _rank(name, ranks, depth)
        for target in targets:
            theirs = _rank(target, ranks, depth) if target.startswith(scope) else None
            if own is not None and theirs is not None and theirs > own:
                upward.append(f"{name} -> {target}")
    assert upward == []


def test_assemblies_stay_apart(graph):
    crossing = []
    for name, targets in graph.items():
        if not name.startswith("roadgrip.cloud."):
            continue
        for apart in CLOUD_APART:
            own = name.split(".")[2]
            if own in apart:
                crossing += [
                    f"{name} -> {t}"
                    for t in targets
                    if t.startswith("roadgrip.cloud.") and t.split(".")[2] in apart - {own}
                ]
    assert crossing == []


def test_domain_and_formats_are_pure(graph):
    """The map, the warnings, the stations and their formats know no transport, storage, settings or service."""
    pure = ("roadgrip.cloud.domain", "roadgrip.cloud.formats")
    allowed_outside = (
        "roadgrip.units",
        "roadgrip.validation",
        "roadgrip.data.schema",
        "roadgrip.data.telemetry",
        "roadgrip.estimators.guard",
    )
    leaks = [
        f"{name} -> {t}"
        for name, targets in graph.items()
        if name.startswith(pure)
        for t in targets
        if not t.startswith(pure) and not t.startswith(allowed_outside)
    ]
    assert leaks == []


def test_nothing_imports_the_benchmarks(graph):
    users = [
        f"{name} -> {t}"
        for name, targets in graph.items()
        for t in targets
        if t.startswith("roadgrip.bench") and not name.startswith(("roadgrip.bench", "roadgrip.cli"))
    ]
    assert users == []


def test_the_rules_catch_a_forbidden_import():
    """The checker itself: an upward import and a circle, made up, are found."""
    fake = {
        "roadgrip.cloud.domain.a": {"roadgrip.cloud.storage.b"},
        "roadgrip.cloud.storage.b": {"roadgrip.cloud.domain.a"},
    }
    assert _cycles(fake) == [["roadgrip.cloud.domain.a", "roadgrip.cloud.storage.b"]]
    assert _rank("roadgrip.cloud.storage.b", CLOUD_RANKS, 2) > _rank("roadgrip.cloud.domain.a", CLOUD_RANKS, 2)


def test_edge_takes_only_what_the_car_shares_with_the_cloud(graph):
    """The vehicle end imports of the cloud only the domain, the topic names and the wire parser; the cloud never
    imports it (docs/ARCHITECTURE.md)."""
    shared = ("roadgrip.cloud.domain", "roadgrip.cloud.transport.mqtt", "roadgrip.cloud.ingest.wire")
    crossing = [
        f"{name} -> {t}"
        for name, targets in graph.items()
        for t in targets
        if (name.startswith("roadgrip.edge") and t.startswith("roadgrip.cloud") and not t.startswith(shared))
        or (name.startswith("roadgrip.cloud") and t.startswith("roadgrip.edge"))
    ]
    assert crossing == []
