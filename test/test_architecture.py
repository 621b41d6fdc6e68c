"""The architecture, enforced: layers point one way, ROS stays in the nodes, no module over 500 lines,
no private name used across modules, benchmarks use the public code only.

Layers, lowest first (a module may import its own subpackage and any lower layer, never a higher one
or another subpackage of its own layer)::

    errors, version < util < model < io < fusion | fitting < simulation < calibration < discovery
        < workflows < imu_array_ros (the public API) < cli | nodes < __main__

Every ``import`` counts, also one inside a function (a lazy import is still a dependency).
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "imu_array_ros"

#: subpackage (or top-level module) -> layer; equal layers may not import each other
LAYERS = {
    "errors": 0, "version": 0,
    "util": 1,
    "model": 2,
    "io": 3,
    "fusion": 4, "fitting": 4,
    "simulation": 5, "timing": 5,
    "calibration": 6,
    "discovery": 7,
    "workflows": 8,
    "": 9,  # imu_array_ros/__init__.py: the public API
    "cli": 10, "nodes": 10,
    "__main__": 11,  # python -m imu_array_ros: the command line
}
#: modules only the nodes may import (the core is ROS-free)
ROS_MODULES = ("rclpy", "sensor_msgs", "geometry_msgs", "std_srvs", "diagnostic_msgs", "builtin_interfaces",
               "std_msgs", "rosidl_runtime_py", "launch", "launch_ros", "ament_index_python", "tf2_msgs",
               "rosgraph_msgs")
MAX_LINES = 500


@dataclass(frozen=True)
class Violation:
    path: str
    line: int
    text: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.text}"


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _unit(module: str, package: str) -> str:
    """The layer unit of a dotted module name: its first component below the package ('' for the root)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _imports(tree: ast.AST, module: str, is_package: bool):
    """(line, imported module, names) for every import of the file, relative ones resolved."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, ()
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base if is_package else base[:-1]
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            yield node.lineno, target, tuple(a.name for a in node.names)


def check_tree(root: Path, package: str = "imu_array_ros", layers: dict = LAYERS,
               ros_units: tuple = ("nodes",), max_lines: int = MAX_LINES) -> list[Violation]:
    """Every violation of the rules in the module docstring under the package directory ``root``."""
    out: list[Violation] = []
    for path in sorted(root.rglob("*.py")):
        rel = str(path.relative_to(root.parent))
        text = path.read_text(encoding="utf-8")
        n_lines = text.count("\n") + (not text.endswith("\n") and bool(text))
        if n_lines > max_lines:
            out.append(Violation(rel, 1, f"{n_lines} lines (at most {max_lines})"))
        module = _module_name(path, root)
        unit = _unit(module, package)
        if unit not in layers:
            out.append(Violation(rel, 1, f"subpackage {unit!r} has no layer"))
            continue
        tree = ast.parse(text, filename=rel)
        imported_modules: dict[str, str] = {}  # local name -> module of the package
        for line, target, names in _imports(tree, module, path.name == "__init__.py"):
            top = target.split(".")[0]
            if top in ROS_MODULES and unit not in ros_units:
                out.append(Violation(rel, line, f"imports {target}: ROS is for {', '.join(ros_units)} only"))
            if top != package:
                continue
            other = _unit(target, package)
            if other == "" and names and target == package:
                # `from imu_array_ros import x`: x may be a subpackage (its layer) or a public-API name
                subs = [n for n in names if n in layers and n != ""]
                for n in subs:
                    imported_modules[n] = f"{package}.{n}"
                others = [_unit(f"{package}.{n}", package) for n in subs] + ([""] if len(subs) < len(names) else [])
            else:
                others = [other]
                for n in names:
                    imported_modules[n] = f"{target}.{n}"
            for o in others:
                if o == unit or o not in layers:
                    continue
                if layers[o] >= layers[unit]:
                    what = "the same layer as" if layers[o] == layers[unit] else "a higher layer than"
                    out.append(Violation(rel, line, f"imports {target} ({o or 'the public API'}): "
                                                    f"{what} {unit or 'the public API'}"))
            if target != module:
                for n in names:
                    if n.startswith("_") and not n.startswith("__"):
                        out.append(Violation(rel, line, f"imports the private name {n} from {target}"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith(package + "."):
                        imported_modules[alias.asname or alias.name] = alias.name
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in imported_modules and node.attr.startswith("_")
                    and not node.attr.startswith("__")):
                out.append(Violation(rel, node.lineno, f"uses the private name {node.value.id}.{node.attr}"))
    return out


def test_the_package_keeps_its_layers():
    violations = check_tree(PACKAGE)
    assert not violations, "\n".join(map(str, violations))


def _write(root: Path, files: dict[str, str]) -> Path:
    pkg = root / "imu_array_ros"
    for rel, text in files.items():
        p = pkg / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return pkg


@pytest.mark.parametrize("files, expected", [
    ({"model/a.py": "from imu_array_ros.io.messages import x\n"}, "a higher layer than model"),
    ({"model/a.py": "def f():\n    import imu_array_ros.fusion.live\n"}, "a higher layer than model"),
    ({"fusion/a.py": "from imu_array_ros.fitting import engine\n"}, "the same layer as fusion"),
    ({"nodes/a.py": "from imu_array_ros.cli.commands import load_array\n"}, "the same layer as nodes"),
    ({"calibration/a.py": "from imu_array_ros import fuse\n"}, "a higher layer than calibration"),
    ({"fusion/a.py": "import rclpy\n"}, "ROS is for nodes only"),
    ({"model/a.py": "from ..calibration.geometry import select\n"}, "a higher layer than model"),
    ({"calibration/a.py": "from imu_array_ros.calibration.b import _helper\n"}, "private name _helper"),
    ({"calibration/a.py": "from imu_array_ros.calibration import b\nb._helper()\n"}, "private name b._helper"),
    ({"util/a.py": "x = 1\n" * 501}, "501 lines"),
    ({"newthing/a.py": "x = 1\n"}, "has no layer"),
])
def test_the_checker_finds_a_deliberate_violation(tmp_path, files, expected):
    pkg = _write(tmp_path, {"__init__.py": "", **files})
    found = check_tree(pkg)
    assert any(expected in str(v) for v in found), found


def test_the_checker_passes_what_is_allowed(tmp_path):
    pkg = _write(tmp_path, {
        "__init__.py": "from imu_array_ros.workflows import fuse\n",
        "fusion/a.py": "from imu_array_ros.model.samples import ImuSamples\nfrom .b import helper\n",
        "fusion/b.py": "def helper():\n    return 1\ndef _own():\n    return _own\n",
        "nodes/n.py": "import rclpy\nfrom imu_array_ros.workflows import load_array\n",
        "cli/c.py": "from imu_array_ros import fuse\n",
    })
    assert check_tree(pkg) == []


BENCHMARKS = ROOT / "benchmarks"


def test_benchmarks_use_the_public_code_only():
    """No sys.path edits (run them as ``python -m benchmarks.<name>``) and no private names of the package."""
    bad = []
    for path in sorted(BENCHMARKS.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name) \
                    and node.value.id == "sys":
                parent_calls = [n for n in ast.walk(tree) if isinstance(n, (ast.Call, ast.Assign, ast.Subscript))
                                and node in ast.walk(n)]
                if any(isinstance(n, ast.Assign) or (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
                       and n.func.attr in ("insert", "append", "extend")) for n in parent_calls):
                    bad.append(f"{path.name}:{node.lineno}: edits sys.path")
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("imu_array_ros"):
                for a in node.names:
                    if a.name.startswith("_") and not a.name.startswith("__"):
                        bad.append(f"{path.name}:{node.lineno}: imports the private {a.name} from {node.module}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("module", ["imu_array_ros", "imu_array_ros.workflows"])
def test_lazy_exports_resolve_and_match_what_type_checkers_see(module):
    """The public API and the workflows layer import their names on first use (PEP 562); every exported name
    resolves, comes from the module the table says, and is imported under ``TYPE_CHECKING`` too (so the
    layer check above and type checkers see the same dependencies)."""
    import importlib

    mod = importlib.import_module(module)
    path = Path(mod.__file__)
    tree = ast.parse(path.read_text(encoding="utf-8"))
    checked: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            checked |= {a.asname or a.name for n in node.body if isinstance(n, ast.ImportFrom) for a in n.names}
    assert set(mod.EXPORTS) == checked
    for name, source in mod.EXPORTS.items():
        value = getattr(mod, name)
        assert getattr(importlib.import_module(source), name) is value, name
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        getattr(mod, "nothing_here")
