"""requirements-worker.txt: exactly what a sweep worker needs — every third-party package the core imports,
pinned as in requirements.txt (and Dask's own dependencies, so a worker installs from one pinned list)."""
import ast
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]
#: import name → distribution name, where they differ
DISTRIBUTION = {"yaml": "PyYAML", "markupsafe": "MarkupSafe", "jinja2": "Jinja2"}
#: imported by the core only on the client, never in a worker's task (the sweep plots; previews of a run)
CLIENT_ONLY = {"matplotlib"}


def pins(path):
    out = {}
    for line in path.read_text().splitlines():
        m = re.match(r"^\s*([A-Za-z0-9_.\-]+)\s*==\s*([^\s#;]+)", line)
        if m:
            out[m.group(1).lower()] = m.group(2)
    return out


def core_third_party_imports():
    names = set()
    for f in (REPO / "core").rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n != "core" and n != "__future__"}


def test_worker_pins_equal_the_project_pins():
    worker, project = pins(REPO / "requirements-worker.txt"), pins(REPO / "requirements.txt")
    assert worker and all(project.get(name) == version for name, version in worker.items()), \
        {n: (v, project.get(n)) for n, v in worker.items() if project.get(n) != v}
    assert "bpy" not in worker  # workers need no Blender


def test_every_package_the_core_imports_is_in_the_worker_list():
    worker = pins(REPO / "requirements-worker.txt")
    needed = {DISTRIBUTION.get(n, n).lower() for n in core_third_party_imports() - CLIENT_ONLY}
    assert {"numpy", "scipy", "embreex", "openexr", "distributed", "cloudpickle"} <= needed
    assert needed <= set(worker), needed - set(worker)


def test_the_worker_list_is_closed_under_dependencies():
    """Every (non-optional) requirement of every listed package is listed too: one pinned list installs a worker."""
    from importlib.metadata import requires

    from packaging.requirements import Requirement

    worker = {k.replace("-", "_") for k in pins(REPO / "requirements-worker.txt")}
    for dist in worker:
        for text in requires(dist) or []:
            req = Requirement(text)
            if req.marker is not None and not req.marker.evaluate({"extra": ""}):
                continue  # an optional extra, or not for this Python
            assert req.name.lower().replace("-", "_") in worker, (dist, text)
