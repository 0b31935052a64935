"""A clone's documentation stands on its own and says how to install; a Blender without the bundled packages
gets a message that says what to do (issue 14)."""
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
import settings_reference  # noqa: E402


def doc_files():
    return [REPO / "README.md"] + sorted((REPO / "docs").rglob("*.md"))


def test_readme_and_docs_link_to_nothing_outside_the_repository():
    """No link to ../shared/ (the developers' folder beside the repository, absent from a clone), and every
    relative Markdown link points at a file of the repository."""
    for path in doc_files():
        text = path.read_text(encoding="utf-8")
        assert "shared/" not in text, f"{path.relative_to(REPO)} mentions shared/"
        for target in re.findall(r"\]\(([^)#\s]+)", text):
            if "://" in target or target.startswith("mailto:"):
                continue
            assert (path.parent / target).resolve().exists(), f"{path.relative_to(REPO)}: broken link {target}"


def test_readme_says_how_to_build_the_zip_for_install_from_disk():
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text[text.index("Install from Disk"):][:1500]
    assert "scripts/build_extension.py" in section and "dist/ladar_simulator-" in section


def test_settings_reference_is_generated_from_the_schema():
    """docs/settings.md is exactly what scripts/settings_reference.py writes, and every setting has a
    description (before: hand-written docs, 3 settings undocumented)."""
    committed = (REPO / "docs" / "settings.md").read_text(encoding="utf-8")
    assert committed == settings_reference.render(), "run python scripts/settings_reference.py"
    assert settings_reference.undocumented() == []
    import dataclasses

    from core.config import GROUPS, BRDFSettings, SimulationConfig
    cfg = SimulationConfig()
    names = [f"{g}.{f.name}" for g in GROUPS for f in dataclasses.fields(getattr(cfg, g))]
    names += [f.name for f in dataclasses.fields(BRDFSettings)] + ["system_type"]
    for name in names:
        assert f"| `{name}` |" in committed, name
    # 90 + gated.min_peak_fraction, k_sigma + atmosphere.scintillation_statistics, inner_scale_m, outer_scale_m
    assert len(names) == 95 + len(dataclasses.fields(BRDFSettings))
    assert "settings.md" in (REPO / "README.md").read_text(encoding="utf-8")


def test_a_blender_without_the_packages_is_told_what_to_install():
    """Loading the add-on package in a Python without site-packages (as a stock Blender lacks scipy, embreex,
    OpenEXR, matplotlib): an ImportError naming them and the build_extension.py zip, instead of
    "No module named 'scipy'" from deep inside the core."""
    code = ("import importlib.util, sys\n"
            f"spec = importlib.util.spec_from_file_location('ladar_simulator', {str(REPO / '__init__.py')!r},\n"
            f"    submodule_search_locations=[{str(REPO)!r}])\n"
            "mod = importlib.util.module_from_spec(spec); sys.modules['ladar_simulator'] = mod\n"
            "try:\n    spec.loader.exec_module(mod)\nexcept ImportError as e:\n    print(e)\n")
    out = subprocess.run([sys.executable, "-S", "-c", code], capture_output=True, text=True, timeout=60)
    msg = out.stdout.strip()
    assert msg.startswith("Ladar Simulator needs the Python package(s) scipy, embreex, OpenEXR, matplotlib"), \
        out.stdout + out.stderr
    assert "scripts/build_extension.py" in msg and "Install from Disk" in msg and "requirements.txt" in msg
