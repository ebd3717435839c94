"""The package's layout holds: no import circles (imports inside functions count too), data
flows one way through the layers (no import runs back up), the protocol imports nothing else of
the package and stays small, and every folder the docs name exists."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "gvbench_nb"
STAGES = ("protocol", "protocol/features", "protocol/matching", "protocol/recipes", "data", "runner")
STAGES += ("evaluation", "verification", "studies", "reporting", "speed")
# Bottom to top: a room (a top-level module or folder of the package) imports only rooms of its
# own layer or below. data -> protocol -> runner -> evaluation and studies -> reporting and the CLI.
LAYERS = (
    ("gvbench_nb", "io_utils", "arguments", "progress"),  # the package face names only its version
    ("protocol",),
    ("data", "imm"),
    ("methods", "reference_values"),
    ("runner",),
    ("evaluation", "verification"),
    ("studies",),
    ("reporting", "notebook"),
    ("explore_lab",),
    ("run_and_publish",),
    ("cli", "__main__"),
    ("speed",),  # the bench: a program of its own that nothing imports
)
PROTOCOL_LINES = 3200  # about 3,000 (with the recipes' references): a reviewer reads it against hloc in one sitting


def module_name(path: Path) -> str:
    return ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(".__init__")


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports anywhere in its body (not under TYPE_CHECKING)."""
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        typing_only = {
            id(sub)
            for node in ast.walk(tree)
            if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
            for sub in ast.walk(node)
        }
        found: set[str] = set()
        for node in ast.walk(tree):
            if id(node) in typing_only:
                continue
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("gvbench_nb"):
                for alias in node.names:
                    full = f"{node.module}.{alias.name}"
                    found.add(full if full in modules else node.module)
            elif isinstance(node, ast.Import):
                found |= {a.name for a in node.names if a.name.startswith("gvbench_nb")}
        graph[name] = {m for m in found if m in modules and m not in (name, "gvbench_nb")}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in graph[node]:
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return found


def test_no_module_imports_one_that_imports_it_back() -> None:
    assert cycles(import_graph()) == []


def test_the_cycle_check_finds_a_circle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_each_stage_is_a_folder_of_the_package() -> None:
    for stage in STAGES:
        assert (PACKAGE / stage / "__init__.py").is_file(), stage


def room(module: str) -> str:
    """The top-level module or folder of the package a module belongs to."""
    return module.split(".")[1] if "." in module else module


def imports_back_up(graph: dict[str, set[str]], layers: tuple[tuple[str, ...], ...]) -> list[str]:
    """Imports from a room to a room of a higher layer, and rooms no layer names."""
    layer_of = {name: i for i, names in enumerate(layers) for name in names}
    found = []
    for module, targets in graph.items():
        if room(module) not in layer_of:
            found.append(f"{module}: its room {room(module)!r} is in no layer")
            continue
        for target in targets:
            if room(target) in layer_of and layer_of[room(target)] > layer_of[room(module)]:
                found.append(f"{module} -> {target}")
    return sorted(found)


def test_no_import_runs_back_up_the_layers() -> None:
    graph = import_graph()
    assert imports_back_up(graph, LAYERS) == []
    rooms: dict[str, set[str]] = {}
    for module, targets in graph.items():
        rooms.setdefault(room(module), set()).update(room(t) for t in targets if room(t) != room(module))
    for target in {t for ts in rooms.values() for t in ts}:
        rooms.setdefault(target, set())
    assert cycles(rooms) == []  # rooms of one layer do not import each other in a loop either


def test_the_layer_check_finds_an_import_back_up() -> None:
    graph = {"gvbench_nb.protocol.images": {"gvbench_nb.runner.store"}, "gvbench_nb.runner.store": set()}
    assert imports_back_up(graph, (("protocol",), ("runner",))) == [
        "gvbench_nb.protocol.images -> gvbench_nb.runner.store"
    ]


def test_the_protocol_imports_nothing_else_of_the_package_and_stays_small() -> None:
    graph = import_graph()
    outside = {
        f"{module} -> {target}"
        for module, targets in graph.items()
        if room(module) == "protocol"
        for target in targets
        if room(target) != "protocol"
    }
    assert outside == set()
    files = [*(PACKAGE / "protocol").rglob("*.py"), *(PACKAGE / "protocol").rglob("*.yaml")]
    lines = sum(len(path.read_text().splitlines()) for path in files)
    assert lines <= PROTOCOL_LINES, f"protocol/ holds {lines} lines"
