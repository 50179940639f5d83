"""The layering of hammer_ros: each layer imports only the layers below it (``LAYERS``), no
import cycles, rclpy only at the ROS edge, and a core that works where rclpy cannot be imported
(``pip install .`` without the ``ros`` extra)."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "hammer_ros"
# the modules that may import rclpy or a ROS message package: the ROS edge only
RCLPY_ALLOWED = ("hammer_ros.ros.",)
# Each layer (a subpackage or a module directly in hammer_ros) and the layers it may import, at
# module level or inside a function, bottom to top. Importing the root package is always allowed.
BASE = {"errors", "process_status"}
LAYERS: dict[str, set[str]] = {
    "errors": set(),
    "process_status": set(),
    "identification": BASE,
    "diagnosis": BASE | {"identification"},
    "streaming": BASE | {"identification", "diagnosis"},
    "messages": BASE | {"identification", "streaming"},
    "io": BASE | {"identification", "diagnosis", "streaming", "messages"},
    "reproduce": BASE | {"identification", "diagnosis", "streaming", "messages", "io"},
    "fleet": BASE | {"identification", "diagnosis", "streaming", "messages", "io"},
    "ros": BASE | {"identification", "diagnosis", "streaming", "messages", "io", "reproduce"},
    "api": BASE | {"identification", "diagnosis", "streaming", "messages", "io"},
    "cli": BASE | {"identification", "diagnosis", "streaming", "messages", "io", "reproduce", "fleet", "ros", "api"},
    "tools": BASE | {"identification", "diagnosis", "streaming", "messages", "io", "reproduce", "fleet", "ros", "api",
                     "cli"},
}
ROS_IMPORTS = ("rclpy", "std_msgs", "sensor_msgs", "geometry_msgs", "diagnostic_msgs", "lifecycle_msgs",
               "rcl_interfaces", "builtin_interfaces", "visualization_msgs", "std_srvs")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Every hammer_ros module that ``name`` imports, at module level or inside a function."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            candidates = [target] + [f"{target}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            candidates = [alias.name for alias in node.names]
        else:
            continue
        for candidate in candidates:
            if candidate in modules:
                found.add(candidate)
            # importing a.b.c imports the packages a and a.b first (but not ``name``'s own packages: they
            # are initialised before ``name``, so ``a.b.c`` importing ``a.b.d`` is no cycle with ``a.b``)
            parts = candidate.split(".")
            found.update(package for package in (".".join(parts[:k]) for k in range(1, len(parts)))
                         if package in modules and not name.startswith(package + "."))
    found.discard(name)
    return found


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components with more than one module (the import cycles)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
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
                cycles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return cycles


def test_no_import_cycles_between_modules():
    modules = all_modules()
    graph = {name: imports_of(name, path, modules) for name, path in modules.items()}
    assert sum(len(edges) for edges in graph.values()) > 100  # the graph was really built
    assert strongly_connected(graph) == []


def layer_of(module: str) -> str:
    """'hammer_ros.io.bag_reader' -> 'io'; '' for the root package."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """Every import of a layer that its allowlist in ``LAYERS`` does not name (the root package
    re-exports the Python API, ``api``, lazily: it is no layer)."""
    return sorted(f"{name} -> {target}" for name, targets in graph.items() if layer_of(name) for target in targets
                  if layer_of(target) not in {"", layer_of(name)} | LAYERS[layer_of(name)])


def test_every_layer_imports_only_the_layers_below_it():
    modules = all_modules()
    assert {layer_of(m) for m in modules} - {""} == set(LAYERS)  # a new layer must be placed in LAYERS
    graph = {name: imports_of(name, path, modules) for name, path in modules.items()}
    assert layer_violations(graph) == []


def test_the_layers_are_an_order():
    """Each allowlist names only layers listed before it, so no two layers can import each other."""
    seen: set[str] = set()
    for layer, allowed in LAYERS.items():
        assert allowed <= seen, layer
        seen.add(layer)


def test_the_layer_check_finds_an_upward_import():
    graph = {"hammer_ros.io.bag_reader": {"hammer_ros.messages.cdr", "hammer_ros.ros.node_core", "hammer_ros"},
             "hammer_ros.ros.node": {"hammer_ros.io.bags", "hammer_ros.ros.node_core"}}
    assert layer_violations(graph) == ["hammer_ros.io.bag_reader -> hammer_ros.ros.node_core"]


def test_the_cycle_finder_finds_a_cycle():
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_only_the_ros_edge_imports_rclpy_and_message_packages():
    offenders = []
    for name, path in all_modules().items():
        if name.startswith(RCLPY_ALLOWED):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            targets = ([a.name for a in node.names] if isinstance(node, ast.Import)
                       else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            offenders += [f"{name}: {t}" for t in targets if t.split(".")[0] in ROS_IMPORTS]
    assert offenders == []


def test_every_layer_says_what_it_holds_and_what_it_may_import():
    """Each subpackage's docstring names what it may import, and ``__all__`` its public names,
    each a submodule or a name bound in the ``__init__``."""
    packages = sorted(p.parent.name for p in PACKAGE.glob("*/__init__.py"))
    assert set(packages) <= set(LAYERS) and len(packages) >= 10
    for package in packages:
        tree = ast.parse((PACKAGE / package / "__init__.py").read_text())
        doc = ast.get_docstring(tree)
        assert doc and len(doc) > 80 and "May import" in doc, package
        if package == "diagnosis":  # its __init__ is being rewritten on the diagnosis branch
            continue
        exported = [ast.literal_eval(node.value) for node in tree.body if isinstance(node, ast.Assign)
                    and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets)]
        assert len(exported) == 1 and exported[0], package
        bound = {alias.asname or alias.name for node in tree.body if isinstance(node, (ast.Import, ast.ImportFrom))
                 for alias in node.names}
        bound |= {node.name for node in tree.body if isinstance(node, (ast.FunctionDef, ast.ClassDef))}
        for name in exported[0]:
            assert name in bound or (PACKAGE / package / f"{name}.py").is_file() or \
                (PACKAGE / package / name / "__init__.py").is_file(), f"{package}.{name}"


# In this child, importing rclpy or any ROS message package fails as on a machine without ROS.
WITHOUT_ROS = """
import importlib, json, sys
BLOCKED = set(sys.argv[1].split(","))

class NoRos:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"No module named {name!r} (blocked: no ROS on this machine)")
        return None

sys.meta_path.insert(0, NoRos())
try:
    import rclpy  # noqa: F401
except ImportError:
    pass
else:
    raise SystemExit("rclpy is still importable")
imported, failed = [], {}
for name in sys.argv[2].split(","):
    try:
        importlib.import_module(name)
        imported.append(name)
    except Exception as exc:
        failed[name] = f"{type(exc).__name__}: {exc}"
from hammer_ros.cli import main
codes = {}
for command in json.loads(sys.argv[3]):
    codes[" ".join(command[:1])] = main(command)
print(json.dumps({"imported": imported, "failed": failed, "codes": codes}))
"""


def test_the_core_works_without_rclpy(tmp_path):
    from hammer_ros.identification.linear import LinearModel
    from hammer_ros.identification.simulate import simulate_hammerstein

    rng = np.random.default_rng(3)
    v = rng.standard_normal(4000)
    g = LinearModel(b=[0.0, 1.0, 0.5], a=[1.0, -1.5, 0.7])
    y = simulate_hammerstein(v, lambda x: x + 0.5 * x**3, g) + 0.01 * rng.standard_normal(v.size)
    record = tmp_path / "record.csv"
    np.savetxt(record, np.column_stack([v, y]), delimiter=",", header="u,y", comments="")
    core = [m for m in all_modules() if not m.startswith(RCLPY_ALLOWED) and not m.endswith("__main__")]
    assert len(core) > 40
    bag, config = REPO / "bags" / "float64_cubic_g1.mcap", REPO / "msg_config" / "float64_cubic_g1.yaml"
    commands = [
        ["identify", str(record), "--order", "2", "--json"],
        ["diagnose", str(record), "--order", "2", "--json"],
        ["replay", str(bag), "--config", str(config), "--out", str(tmp_path / "out.mcap"), "--json"],
    ]
    done = subprocess.run([sys.executable, "-c", WITHOUT_ROS, ",".join(ROS_IMPORTS), ",".join(core),
                           json.dumps(commands)], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["failed"] == {}
    assert sorted(report["imported"]) == sorted(core)
    assert report["codes"] == {"identify": 0, "diagnose": 0, "replay": 0}
    assert (tmp_path / "out.mcap").stat().st_size > 0
