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
    # + run.max_work_s; + 13 of issue 29: laser.beam_divergence_y_rad, beam_orientation_rad, scanner.return_mode,
    # n_returns, range_quantum_m, intensity_encoding and the 7 table fields (channel_table, channel_table_file,
    # risley_prism_hz, risley_wedge_deg, risley_index, risley_phase_deg, risley_emitters_deg)
    # + 8 of issue 30: atmosphere.weather, rain_rate_mm_h, backscatter_per_m_sr, lidar_ratio_sr, overlap_model,
    # tx_rx_offset_m, backscatter_min_range_m, drop_min_diameter_mm; + 1 of issue 28: detection.signal_free_bins
    # (noisy_threshold_mode existed; its new choice "calibrated" is its default); + 2 of session 27:
    # atmosphere.drop_cut_photoelectrons (issue 30) and scanner.cone_half_angle_y_rad (issue 29: the elliptic
    # Palmer cone); + 2 of session 28 (issue 30): atmosphere.tx_rx_offset_angle_deg, aerosol_layers; + 4 of issue 29
    # (sunlight reflected by the scene): atmosphere.solar_irradiance_w_m2_nm, sun_elevation_rad, sun_azimuth_rad,
    # receiver.filter_bandwidth_m; + 2 of session 29 (issue 28): run.save_counts, gate.binning (the tabulated
    # pulse ⊛ box or the exact binning)
    # + 1 of session 30 (issue 28): scanner.pulse_model (the centroid pulse or the sub-ray sum)
    assert len(names) == 129 + len(dataclasses.fields(BRDFSettings))
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


# --------------------------------------------------------------------------------------------------------------
# docs/theory.md is the physics reference the code cites (issue 14c)
# --------------------------------------------------------------------------------------------------------------
#: The developers' private reference sheet, absent from a clone (split so that this file does not cite it).
PRIVATE_SHEET = "physics" + ".md"
SECTION_ITEM = r"§(\d+)(?:\s*[–-]\s*(\d+))?"
CITATION = re.compile(rf"theory\.md`*\s+({SECTION_ITEM}(?:\s*,\s*{SECTION_ITEM})*)")
LINK = re.compile(r"\[theory ([^\]]+)\]\(([^)#\s]*theory\.md)#([^)\s]+)\)"
                  r"|\[(§[^\]]+)\]\(([^)#\s]*theory\.md)#([^)\s]+)\)")


def tracked_text_files():
    """(relative path, text) of every text file git tracks (the files a clone gets)."""
    out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    for rel in out.decode().split("\0"):
        path = REPO / rel
        if not rel or not path.is_file() or path.stat().st_size > 2_000_000:
            continue
        try:
            yield rel, path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue


def section_numbers(items: str) -> list[int]:
    nums = []
    for a, b in re.findall(SECTION_ITEM, items):
        nums += list(range(int(a), int(b or a) + 1))
    return nums


def test_theory_has_the_fourteen_numbered_sections():
    sections = settings_reference.theory_sections()
    assert sorted(sections) == list(range(1, 15))
    assert sections[3] == "3-log-intensity-variance-aperture-averaging-and-intensity-pdfs"
    assert settings_reference.github_slug("4. Gaussian beam: spread and wander") == "4-gaussian-beam-spread-and-wander"


def test_nothing_cites_the_private_physics_sheet():
    """Before: about 170 citations of the sheet in code, docs, scripts, bench, tests and presets pointed at a file
    a clone does not have; now every one names docs/theory.md."""
    this = str(Path(__file__).resolve().relative_to(REPO))  # names the patterns it looks for
    offenders = [f"{rel}:{n}" for rel, text in tracked_text_files() if rel not in ("docs/theory.md", this)
                 for n, line in enumerate(text.splitlines(), 1)
                 if PRIVATE_SHEET in line or "shared/reference" in line
                 or re.search(r"\bphysics §\d|\bsheet's\b|\(sheet\b|physics sheet", line)]
    assert offenders == [], offenders


def test_every_theory_citation_names_an_existing_section():
    """Plain citations ("docs/theory.md §3", "§1–6, §11–13") and Markdown links (text "theory §3" to
    theory.md#anchor): each section number exists, and a link's anchor is the heading of the section it names."""
    sections = settings_reference.theory_sections()
    n_plain = n_links = 0
    for rel, text in tracked_text_files():
        for m in CITATION.finditer(text):
            nums = section_numbers(m.group(1))
            assert nums and all(n in sections for n in nums), f"{rel}: {m.group(0)!r}"
            n_plain += 1
        for m in LINK.finditer(text):
            label, target, anchor = (m.group(1), m.group(2), m.group(3)) if m.group(1) else m.group(4, 5, 6)
            nums = section_numbers(label)
            assert nums and nums[0] in sections, f"{rel}: {m.group(0)!r}"
            assert anchor == sections[nums[0]], f"{rel}: {m.group(0)!r} should link #{sections[nums[0]]}"
            assert ((REPO / rel).parent / target).resolve() == REPO / "docs" / "theory.md", f"{rel}: {target}"
            n_links += 1
    assert n_plain >= 100 and n_links >= 10, (n_plain, n_links)  # the patterns still match the citations


def test_theory_anchors_inside_the_docs_resolve():
    """Every link to a heading of docs/theory.md (from the docs, the README and theory.md's own contents line)
    names a heading that exists."""
    slugs = set(settings_reference.theory_sections().values()) | {"references"}
    theory = (REPO / "docs" / "theory.md").read_text(encoding="utf-8")
    for path in doc_files():
        text = path.read_text(encoding="utf-8")
        anchors = re.findall(r"\]\((?:[^)#\s]*theory\.md)#([^)\s]+)\)", text)
        if path.name == "theory.md":
            anchors += re.findall(r"\]\(#([^)\s]+)\)", text)
        for a in anchors:
            assert a in slugs, f"{path.relative_to(REPO)}: #{a}"
    assert "](docs/theory.md)" in (REPO / "README.md").read_text(encoding="utf-8")  # in the documentation table
    assert theory.count("\n## ") >= 14
