"""The import rules of docs/architecture.md, checked with plain ``ast`` over every import of the extension's own
modules (module level, inside functions, under ``if``/``try``):

* core/ is layered; a module imports only from its own layer or the layers below (table ``CORE_LAYERS``);
* a sensor system never imports another system; systems and file output never import each other;
* nothing imports through the ``core`` package namespace (core/__init__.py holds only the version and the old
  import paths), and core never imports bpy or the Blender side;
* no module imports a private ``_name`` from another module;
* core/ imports its own modules at module level (deferred imports only for optional heavy libraries and the
  start-up deferrals listed in ``DEFERRED_OWN``);
* there is no import cycle in core/ or in ladar_addon/;
* ladar_addon/ never imports operators/ or panels/ (the UI sits on top of it), and its fields mapping imports no
  Blender at all.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("core", "ladar_addon", "operators", "panels")

#: layer of each part of core/ (by its dotted prefix; the longest prefix wins), bottom = 0
CORE_LAYERS = {
    "core.constants": 0, "core.errors": 0, "core.version": 0, "core.process": 0, "core.jit": 0, "core.threads": 0,
    "core.heap": 0, "core.lazy": 0,
    "core.config": 1,
    "core.geometry": 2, "core.atmosphere": 2,
    "core.atmosphere.weather": 3,  # the weather returns: waveform rows built with core.physics (laser, waveform)
    "core.physics": 3,
    "core.engine": 4,
    "core.systems": 5, "core.fileio": 5,
    "core.run": 6, "core.sequence": 6, "core.warmup": 6,
    "core.sweep": 7,
    "core.presets": 1, "core.presets.checks": 6,  # the preset registry (settings); its data-sheet checks run frames
}
#: the sensor systems (modules that may not import each other); their helpers (scan_patterns) are ordinary modules
SYSTEM_MODULES = {"core.systems.flash", "core.systems.scanner", "core.systems.gated"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _sources() -> dict[str, Path]:
    files = {}
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            files[_module_name(path)] = path
    return files


SOURCES = _sources()


def _is_package(name: str) -> bool:
    return SOURCES.get(name, Path()).name == "__init__.py"


def _imports(name: str, path: Path):
    """(line, imported module, imported names or None) for every import statement of module ``name``."""
    package = name if _is_package(name) else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, None
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".") if package else []
                base = base[:len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            yield node.lineno, module, [a.name for a in node.names]


def _edges():
    """(importer, imported module of ours, line, names) for every import of one of our modules."""
    out = []
    for name, path in SOURCES.items():
        for line, module, names in _imports(name, path):
            if module.split(".")[0] not in PACKAGES and module != "":
                continue
            if names is None:
                out.append((name, module, line, None))
                continue
            # `from package import submodule` imports the submodule; other names come from the module itself
            plain = [n for n in names if f"{module}.{n}".lstrip(".") not in SOURCES]
            for n in names:
                if f"{module}.{n}".lstrip(".") in SOURCES:
                    out.append((name, f"{module}.{n}".lstrip("."), line, None))
            if plain:
                out.append((name, module, line, plain))
    return out


EDGES = _edges()


def _layer(module: str) -> int | None:
    best = None
    for prefix, layer in CORE_LAYERS.items():
        if (module == prefix or module.startswith(prefix + ".")) and (best is None or len(prefix) > len(best[0])):
            best = (prefix, layer)
    return None if best is None else best[1]


def test_every_core_module_has_a_layer():
    assert [m for m in SOURCES if m.startswith("core.") and _layer(m) is None] == []


def test_no_core_import_points_up_a_layer():
    bad = [f"{src}:{line} imports {dst} (layer {_layer(src)} → {_layer(dst)})"
           for src, dst, line, _ in EDGES
           if src.startswith("core.") and dst.startswith("core.") and _layer(dst) > _layer(src)]
    assert bad == []


def test_systems_never_import_each_other_nor_file_output():
    bad = [f"{src}:{line} imports {dst}" for src, dst, line, _ in EDGES
           if (src in SYSTEM_MODULES and (dst in SYSTEM_MODULES or dst.startswith("core.fileio")) and dst != src)
           or (src.startswith("core.fileio") and dst.startswith("core.systems"))]
    assert bad == []


def test_nothing_imports_through_the_core_package():
    bad = [f"{src}:{line} imports {names} from the core package" for src, dst, line, names in EDGES
           if dst == "core" and names]
    bad += [f"{src}:{line} imports core" for src, dst, line, names in EDGES if dst == "core" and not names
            and src != "core"]
    assert bad == []


def test_core_never_imports_blender():
    bad = [f"{name}:{line} imports {module}" for name, path in SOURCES.items() if name.split(".")[0] == "core"
           for line, module, _ in _imports(name, path)
           if module.split(".")[0] in ("bpy", "bmesh", "mathutils", "addon_utils", "ladar_addon", "operators",
                                       "panels")]
    assert bad == []


def test_no_private_name_crosses_a_module():
    bad = [f"{src}:{line} imports {n} from {dst}" for src, dst, line, names in EDGES if names and dst != src
           for n in names if n.startswith("_") and not n.startswith("__")]
    assert bad == []


def test_the_blender_side_is_a_one_way_chain():
    bad = [f"{src}:{line} imports {dst}" for src, dst, line, _ in EDGES
           if src.startswith("ladar_addon") and dst.split(".")[0] in ("operators", "panels")]
    assert bad == []


def _deferred_imports(name: str, path: Path):
    """(line, imported module) of the imports inside functions of module ``name``."""
    package = name if _is_package(name) else name.rpartition(".")[0]
    for fn in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for node in ast.walk(fn):
                if isinstance(node, ast.ImportFrom):
                    base = package.split(".")[:len(package.split(".")) - node.level + 1] if node.level else []
                    yield node.lineno, ".".join(base + ([node.module] if node.module else []))
                elif isinstance(node, ast.Import):
                    for alias in node.names:
                        yield node.lineno, alias.name


#: the only deferred imports of core's own modules, each for start-up (issue 25: a command loads what it uses):
#: (importer, imported module as the checker sees it) -> why.  The checker still sees them (layers, cycles).
DEFERRED_OWN = {
    ("core.run", "core.systems"): "each system's module (and kernels) at its first frame: SYSTEMS",
    ("core.engine.products", "core.physics.detection"): "the noisy detection, only with a noisy receiver",
    ("core.engine.products", "core.physics.receiver"): "the receiver chain, only with a noisy receiver",
    ("core.engine.products", "core.physics.receiver.chain"): "the receiver chain, only with a noisy receiver",
    ("core.engine.products", "core.physics.receiver.conversions"): "(with the two above)",
    ("core.engine.products", "core.physics.detection.false_alarms"): "(with the two above)",
    ("core.engine.products", "core.physics.detection.noisy"): "(with the two above)",
    ("core.engine.products", "core.physics.detection.stretches"): "(with the two above)",
    ("core.systems.flash", "core.physics.receiver.chain"): "the receiver chain, only with a noisy receiver",
    ("core.systems.gated", "core.physics.receiver.chain"): "the receiver chain, only with a noisy receiver",
}


def test_core_defers_no_import_of_its_own_modules():
    """In core/, a deferred (function-level) import is for an optional heavy library only (matplotlib, OpenEXR,
    embreex) or one of :data:`DEFERRED_OWN` (start-up): every other dependency on another module of the
    simulator stands at the top of the module."""
    bad = [f"{name}:{line} imports {module} inside a function" for name, path in SOURCES.items()
           if name.startswith("core.") for line, module in _deferred_imports(name, path)
           if module.split(".")[0] == "core" and (name, module) not in DEFERRED_OWN]
    assert bad == []
    assert ("ladar_addon.cli", "ladar_addon.job") in {  # the check sees imports inside functions
        (n, m) for n in ("ladar_addon.cli",) for _, m in _deferred_imports(n, SOURCES[n])}


def test_the_fields_mapping_needs_no_blender():
    name = "ladar_addon.fields"
    assert name in SOURCES
    blender = [m for _, m, _ in _imports(name, SOURCES[name]) if m.split(".")[0] in ("bpy", "bmesh", "mathutils")]
    ours = [m for _, m, _ in _imports(name, SOURCES[name]) if m.startswith("ladar_addon")]
    assert blender == [] and ours == []


def _cycles(prefix: str) -> list[list[str]]:
    graph = {m: set() for m in SOURCES if m == prefix or m.startswith(prefix + ".")}
    for src, dst, _, _ in EDGES:
        if src in graph and dst in graph and src != dst:
            graph[src].add(dst)
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


@pytest.mark.parametrize("package", ["core", "ladar_addon"])
def test_no_import_cycle(package):
    assert _cycles(package) == []


def test_the_checker_sees_what_it_must():
    """The rules above are not vacuous: the edge list holds function-level imports, relative imports resolve,
    and a made-up cycle, an upward import and a private import would be caught."""
    assert ("ladar_addon.cli", "ladar_addon.job") in {(s, d) for s, d, _, _ in EDGES}  # in a function
    assert ("core.fileio.preview", "core.fileio.run_folder") in {(s, d) for s, d, _, _ in EDGES}
    assert ("core.run", "core.systems.flash") in {(s, d) for s, d, _, _ in EDGES}
    assert _layer("core.physics.receiver.chain") == 3 and _layer("core.engine.frame") == 4
    EDGES.append(("core.geometry.scene", "core.geometry.trace", 0, ["_private"]))
    EDGES.append(("core.geometry.trace", "core.geometry.scene", 0, None))
    try:
        assert _cycles("core") == [["core.geometry.scene", "core.geometry.trace"]]
        with pytest.raises(AssertionError):
            test_no_private_name_crosses_a_module()
    finally:
        del EDGES[-2:]
    EDGES.append(("core.physics.laser", "core.engine.frame", 0, ["open_frame"]))
    try:
        with pytest.raises(AssertionError):
            test_no_core_import_points_up_a_layer()
    finally:
        EDGES.pop()
