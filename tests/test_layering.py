"""The layering of the code's rooms (issue 21 §6): which package may import which.

A package here is a directory under `server/` or `core/`, or a top-level module (`server/messages.py`). An
import anywhere in a file counts, a function-level one included: a circle hidden in a function is still
a circle.

- The paper's science (`core`) imports nothing of the product (`server`).
- The robot side (the daemon, the real-time worker, the HAL) never imports the web side (`sessions`, the
  other route packages, any `routes` module): the daemon decides and records runs, the web side asks and
  reads.
- No new import circle between packages. The circles that remain are listed below, each with what ties
  it, so that the list only shrinks: a circle that disappears must leave the list too.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

ROBOT_SIDE = {"robotd", "realtime", "hal"}
# The web side: packages of routes and what only they use. The robot daemon may read the clinic's records
# (bookings, prescriptions, patients: their models and services) but never a route.
WEB_SIDE = {"sessions", "reports", "exports", "viz", "app", "api_docs", "api_types"}

# What still ties these packages into one circle: `db` imports every table for the metadata, and the object
# authorisation (`auth.access`), the audit trail and the daemon's run rules (`robotd.runs`, which read
# bookings, prescriptions and patients) are each used by, and use, the domain packages.
DOMAIN_CIRCLE = "audit auth db observability patients prescriptions reviews robotd scheduling settings users"
KNOWN_CIRCLES = {
    frozenset({"messages", "realtime"}),  # the error codec rebuilds the worker's TransitionRefused
    frozenset(DOMAIN_CIRCLE.split()),
}

# The twin's IK flags collisions with core.clearance, which builds on the kinematics (a function-level import).
KNOWN_CORE_CIRCLES = {frozenset({"clearance", "kinematics"})}


def package_of(path: Path, top: str) -> str:
    parts = path.relative_to(ROOT / top).with_suffix("").parts
    return parts[0]


def imports_of(path: Path, top: str) -> list[str]:
    """The modules of `top` that one file imports, anywhere in it."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found += [f"{top}.{a.name}" for a in node.names] if node.module == top else [node.module]
        elif isinstance(node, ast.Import):
            found += [a.name for a in node.names]
    return [module for module in found if module.split(".")[0] == top and "." in module]


def import_graph(top: str) -> dict[str, dict[str, set[str]]]:
    """{package: {imported package: {files that import it}}}, within `top`."""
    graph: dict[str, dict[str, set[str]]] = defaultdict(lambda: defaultdict(set))
    for path in sorted((ROOT / top).rglob("*.py")):
        source = package_of(path, top)
        for module in imports_of(path, top):
            target = module.split(".")[1]
            if target != source:
                graph[source][target].add(str(path.relative_to(ROOT)))
    return graph


def circles(graph: dict[str, dict[str, set[str]]]) -> set[frozenset[str]]:
    """The strongly connected components of more than one package (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: set[frozenset[str]] = set()

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for successor in graph.get(node, {}):
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = set()
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.add(member)
                if member == node:
                    break
            if len(component) > 1:
                found.add(frozenset(component))

    for node in sorted(set(graph) | {d for targets in graph.values() for d in targets}):
        if node not in index:
            visit(node)
    return found


def test_the_science_imports_nothing_of_the_product() -> None:
    offenders = sorted(
        f"{path}: imports server" for path in (ROOT / "core").rglob("*.py") if imports_of(path, "server")
    )
    assert not offenders, offenders


def test_the_robot_side_never_imports_the_web_side() -> None:
    offenders = sorted(
        f"{path.relative_to(ROOT)} imports {module}"
        for side in sorted(ROBOT_SIDE)
        for path in (ROOT / "server" / side).rglob("*.py")
        for module in imports_of(path, "server")
        if module.split(".")[1] in WEB_SIDE or module.split(".")[-1] == "routes"
    )
    assert not offenders, "the robot side imports the web side: " + ", ".join(offenders)


def test_no_new_import_circle_between_packages() -> None:
    graph = import_graph("server")
    found = circles(graph)
    new = found - KNOWN_CIRCLES
    gone = KNOWN_CIRCLES - found
    assert not new, "a new import circle between packages: " + "; ".join(" ↔ ".join(sorted(circle)) for circle in new)
    assert not gone, "a known circle is gone or changed: take it out of KNOWN_CIRCLES: " + "; ".join(
        " ↔ ".join(sorted(circle)) for circle in gone
    )
    assert circles(import_graph("core")) == KNOWN_CORE_CIRCLES, "the science's import circles changed"


def test_the_circle_finder_finds_a_circle_and_only_one() -> None:
    graph = {"a": {"b": {"x"}}, "b": {"c": {"x"}}, "c": {"a": {"x"}}, "d": {"a": {"x"}}}
    assert circles(graph) == {frozenset({"a", "b", "c"})}
    assert circles({"a": {"b": {"x"}}}) == set()
