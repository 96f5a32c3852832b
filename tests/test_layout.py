"""The layout's rules (docs/design.md), checked on the source with ``ast``: which floor
may import which, that only the kernel modules touch the compiled core, that no
production module leans on the NumPy references, and that the method packages stay
apart."""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "python" / "tpscore"

#: The modules that bind a C++ kernel family (one each, plus the thread pool's).
KERNEL_MODULES = {"rbf", "csrbf", "spatial", "mesh", "sparse", "raster", "lattice", "registration_terms",
                  "skin_sim", "_threads"}
#: What every floor may lean on: the kernels and the shared helpers.
BASE = KERNEL_MODULES | {"_core", "_validation", "_files", "_version", "geometry"}
METHODS = {"expression", "adaptation", "elastic", "physics"}
#: The package of procedural and demo faces, pictures and the result page.
SHOWCASE = "showcase"
#: What each floor may import (beyond itself); the top level (``tpscore/__init__``),
#: ``cli``, ``batch`` and ``rigging`` tie everything together.
ALLOWED = {
    **{kernel: BASE for kernel in KERNEL_MODULES},
    "geometry": {"_validation"},
    "_validation": set(),
    "_files": {"_validation"},
    "reference": BASE - {"_core"} | {"physics"},
    "face": BASE,
    **{method: BASE | {"face"} for method in METHODS},
    SHOWCASE: BASE | {"face"} | METHODS,
}
#: The two crossings between methods, each through the adaptation's public function: the
#: physical skin is the adaptation's last stage and fits its head with it; the transfer's
#: adapted correspondence fits the target's grid onto the source with it.
METHOD_CROSSINGS = {("physics", "adaptation"), ("expression", "adaptation")}


def _sources():
    if not PACKAGE.is_dir():
        pytest.skip("the package's sources are not beside the tests (installed package)")
    return sorted(PACKAGE.rglob("*.py"))


def _module(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(["tpscore", *parts])


def _is_module(dotted: str) -> bool:
    relative = Path(*dotted.split(".")[1:])
    return (PACKAGE / relative).with_suffix(".py").is_file() or (PACKAGE / relative / "__init__.py").is_file() \
        or (dotted == "tpscore._core")


def _imports(path: Path, top_level_only: bool = False) -> set[str]:
    """Every tpscore module the file imports: at any depth of its code, or only in the
    module's own body."""
    name = _module(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = set()
    for node in (tree.body if top_level_only else ast.walk(tree)):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names if alias.name.split(".")[0] == "tpscore"}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module.split(".")[0] != "tpscore":
                continue
            for alias in node.names:
                candidate = f"{module}.{alias.name}"
                found.add(candidate if _is_module(candidate) else module)
    return found


def _floor(module: str) -> str:
    parts = module.split(".")
    return "tpscore" if len(parts) == 1 else parts[1]


def _graph():
    return {_module(path): _imports(path) for path in _sources()}


def test_only_kernel_modules_import_the_compiled_core():
    offenders = sorted(module for module, imported in _graph().items()
                       if "tpscore._core" in imported and _floor(module) not in KERNEL_MODULES)
    assert not offenders, f"these call tpscore._core outside a kernel module: {offenders}"


def test_no_production_module_imports_the_numpy_references():
    offenders = sorted((module, target) for module, imported in _graph().items() for target in imported
                       if _floor(target) == "reference" and _floor(module) != "reference")
    assert not offenders, f"production code imports tpscore.reference: {offenders}"


def test_each_floor_imports_only_what_it_may():
    offenders = []
    for module, imported in _graph().items():
        floor = _floor(module)
        if floor not in ALLOWED:
            continue  # the top level, cli, batch, rigging: they tie the floors together
        for target in imported:
            other = _floor(target)
            if other == floor or other in ALLOWED[floor] or (floor, other) in METHOD_CROSSINGS:
                continue
            offenders.append(f"{module} -> {target}")
    assert not offenders, "imports across the layout's rules:\n" + "\n".join(sorted(offenders))


def test_the_one_method_crossing_uses_the_public_function_only():
    for module, imported in _graph().items():
        if _floor(module) == "physics":
            crossing = {target for target in imported if _floor(target) == "adaptation"}
            assert crossing <= {"tpscore.adaptation"}, f"{module} reaches inside the adaptation: {crossing}"


def test_neither_face_nor_a_method_imports_the_showcase():
    offenders = sorted((module, target) for module, imported in _graph().items() for target in imported
                       if _floor(module) in {"face"} | METHODS and _floor(target) == SHOWCASE)
    assert not offenders, offenders


def test_the_package_has_no_import_cycle_at_module_level():
    # Imports inside functions are left out: a cycle through one is resolved at call
    # time. A module importing its own package (``from . import x``) is not a cycle.
    graph = {_module(path): _imports(path, top_level_only=True) for path in _sources()}
    state: dict[str, str] = {}

    def visit(node, trail):
        state[node] = "open"
        for target in sorted(graph.get(node, ())):
            if target not in graph or node.startswith(target + "."):
                continue
            if state.get(target) == "open":
                raise AssertionError("import cycle: " + " -> ".join([*trail, node, target]))
            if target not in state:
                visit(target, [*trail, node])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [])


#: The longest a function may be (lines, its docstring included): a longer one is a
#: sequence of steps that wants names.
MAX_FUNCTION_LINES = 120


def test_no_function_is_longer_than_the_limit():
    long = []
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long.append(f"{_module(path)}.{node.name}: {lines} lines")
    assert not long, long
