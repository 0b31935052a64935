"""The manifest passes Blender's own extension validation, and a built package holds only the extension."""
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BL_PKG = Path(sys.prefix) / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / \
    "site-packages" / "bpy"


def _bl_pkg() -> Path:
    """Blender's extension tooling (``blender_ext.py``, what ``blender -c extension validate`` runs)."""
    import importlib.util
    spec = importlib.util.find_spec("bpy")
    root = Path(spec.origin).parent if spec and spec.origin else BL_PKG
    hits = sorted(root.glob("*/scripts/addons_core/bl_pkg"))
    assert hits, f"Blender's bl_pkg not found under {root}"
    return hits[-1]


def _run_blender_ext(*args):
    pkg = _bl_pkg()
    tags = pkg.parent.parent / "modules" / "_bpy_internal" / "extensions" / "tags.py"
    return subprocess.run([sys.executable, str(pkg / "cli" / "blender_ext.py"), *args, "--valid-tags", str(tags)],
                          capture_output=True, text=True, timeout=120)


def test_manifest_fields():
    data = tomllib.loads((REPO / "blender_manifest.toml").read_text())
    assert data["id"] == "ladar_simulator"
    assert data["name"] == "Ladar Simulator"
    assert data["version"] == "0.1.0"
    assert data["type"] == "add-on"
    assert data["blender_version_min"] == "4.2.0"
    assert data["blender_version_max"] == "5.1.0"
    assert data["license"] == ["SPDX:GPL-3.0-or-later"]
    assert data["permissions"]["files"].startswith("Write simulation results")
    excluded = data["build"]["paths_exclude_pattern"]
    for pattern in ("/.venv/", "/.git/", "/tests/", "__pycache__/", "/runs/", "/.pytest_cache/"):
        assert pattern in excluded


def test_blender_validates_the_repository_root():
    proc = _run_blender_ext("validate", str(REPO))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Success" in proc.stdout


def test_built_package_is_valid_and_excludes_development_files(tmp_path):
    proc = _run_blender_ext("build", "--source-dir", str(REPO), "--output-dir", str(tmp_path))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (archive,) = tmp_path.glob("ladar_simulator-0.1.0*.zip")
    names = zipfile.ZipFile(archive).namelist()
    for required in ("blender_manifest.toml", "__init__.py", "core/config/settings.py", "core/systems/flash.py",
                     "ladar_addon/properties.py", "operators/simulate.py", "panels/sensor.py"):
        assert required in names
    for name in names:
        top = name.split("/")[0]
        assert top not in {".venv", ".git", "tests", "runs", "bench", "scripts", ".pytest_cache"}, name
        assert "__pycache__" not in name and not name.endswith(".pyc"), name
    proc = _run_blender_ext("validate", str(archive))
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.parametrize("bad, message", [("blender_version_max = \"5.1.0\"", "blender_version_max"),
                                           ("id = \"ladar_simulator\"", "id")])
def test_validation_catches_a_broken_manifest(tmp_path, bad, message):
    """The validation test is not vacuous: a manifest with a broken field fails."""
    text = (REPO / "blender_manifest.toml").read_text()
    broken = text.replace(bad, bad.split("=")[0] + "= 42")
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "blender_manifest.toml").write_text(broken)
    (pkg / "__init__.py").write_text("")
    proc = _run_blender_ext("validate", str(pkg))
    assert proc.returncode != 0
    assert message in proc.stdout + proc.stderr
