#!/usr/bin/env python3
"""Write docs/settings.md, the settings reference, from the settings schema (core/config/settings.py).

    python scripts/settings_reference.py           # (re)write docs/settings.md
    python scripts/settings_reference.py --check   # exit 1 if docs/settings.md differs from the schema

Every setting of :class:`core.config.SimulationConfig` (and the per-material BRDF settings) with its default,
unit, allowed values and description, as ``core.config.setting`` declares them; nothing is written by hand, so
the reference cannot drift from the code (tests/test_settings_reference.py checks the committed file).
"""
from __future__ import annotations

import argparse
import dataclasses
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from core.config import GROUPS, SCHEMA_VERSION, BRDFSettings, SimulationConfig  # noqa: E402
from core.config.settings import panel_unit  # noqa: E402
from core.presets import list_presets, load_preset  # noqa: E402

OUT = REPO / "docs" / "settings.md"
THEORY = REPO / "docs" / "theory.md"
#: One section of a citation: "§3" or a range "§1–6".
_SECTION = r"§(\d+)(?:[–-]\d+)?"
#: A plain citation of the physics reference in a description: "docs/theory.md §3" or "docs/theory.md §1–6, §11".
_THEORY_CITATION = re.compile(rf"docs/theory\.md ({_SECTION}(?:, {_SECTION})*)")


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a Markdown heading: lower case, punctuation dropped, spaces become hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def theory_sections() -> dict:
    """Section number → anchor of the numbered sections ("## N. Title") of docs/theory.md."""
    text = THEORY.read_text(encoding="utf-8")
    return {int(m.group(1)): github_slug(m.group(0)[3:]) for m in re.finditer(r"^## (\d+)\. .+$", text, re.M)}


def link_theory(text: str) -> str:
    """The descriptions cite the physics reference as "docs/theory.md §N" (or "§1–6, §11"); in docs/settings.md,
    beside it, each cited section becomes a Markdown link to its heading in theory.md."""
    sections = theory_sections()

    def links(m):
        out = []
        for i, item in enumerate(re.findall(r"§\d+(?:[–-]\d+)?", m.group(1))):
            anchor = sections[int(re.match(_SECTION, item).group(1))]
            out.append(f"[{'theory ' if i == 0 else ''}{item}](theory.md#{anchor})")
        return ", ".join(out)
    return _THEORY_CITATION.sub(links, text)


def _number(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:g}"
    return repr(v) if isinstance(v, str) else str(v)


def allowed(f: dataclasses.Field) -> str:
    """The allowed values of a setting as the validator checks them."""
    meta = f.metadata
    if meta.get("choices"):
        names = meta.get("choice_labels") or {}
        return ", ".join(f"`{c}`" + (f" ({names[c]})" if c in names else "") for c in meta["choices"])
    if isinstance(f.default, bool):
        return "true, false"
    if meta.get("allowed"):  # a table field stating its own rule (core/config/tables.py checks it)
        return meta["allowed"]
    if f.default is dataclasses.MISSING and f.default_factory is list:
        return "list of numbers"
    lo, hi = meta.get("lo"), meta.get("hi")
    if lo is None and hi is None:
        return "any"
    left = "(" if meta.get("lo_open") else "["
    right = ")" if meta.get("hi_open") else "]"
    kind = "integer" if isinstance(f.default, int) else "number"
    return f"{kind} in {left}{'-inf' if lo is None else _number(lo)}, {'inf' if hi is None else _number(hi)}{right}"


def _cell(text: str) -> str:
    return link_theory(text.replace("|", "\\|").replace("\n", " "))


HEADER = ["| setting | default | unit | in the panels | allowed | description |", "|---|---|---|---|---|---|"]


def panel(f: dataclasses.Field) -> str:
    """The label of the setting's panel field and the unit the panel shows its value in."""
    label = f.metadata.get("label") or ""
    unit = panel_unit(f.metadata)
    if f.metadata.get("subtype") == "DISTANCE" and not f.metadata.get("panel_unit"):
        unit = "m, the scene's length unit"
    return f"{label} ({unit})" if unit and label else label


def row(f: dataclasses.Field, name: str, default) -> str:
    return (f"| `{name}` | {_cell(_number(default))} | {f.metadata.get('unit') or ''} | {_cell(panel(f))} | "
            f"{_cell(allowed(f))} | {_cell(f.metadata.get('doc', ''))} |")


def table(cls, prefix: str) -> list[str]:
    rows = list(HEADER)
    obj = cls()
    for f in dataclasses.fields(cls):
        rows.append(row(f, f"{prefix}{f.name}", getattr(obj, f.name)))
    return rows


def undocumented() -> list[str]:
    """Settings declared without a description (should be none)."""
    out = []
    for f in dataclasses.fields(SimulationConfig):
        if f.name in GROUPS:
            out += [f"{f.name}.{g.name}" for g in dataclasses.fields(f.type if not isinstance(f.type, str)
                                                                    else type(getattr(SimulationConfig(), f.name)))
                    if not g.metadata.get("doc")]
        elif f.name != "materials" and not f.metadata.get("doc"):
            out.append(f.name)
    out += [f"materials.<name>.{g.name}" for g in dataclasses.fields(BRDFSettings) if not g.metadata.get("doc")]
    return out


def render() -> str:
    cfg = SimulationConfig()
    n = sum(len(dataclasses.fields(type(getattr(cfg, g)))) for g in GROUPS) + 1
    lines = [
        "# Settings reference",
        "",
        "<!-- Generated by scripts/settings_reference.py from core/config/settings.py: do not edit by hand. -->",
        "",
        f"Every setting of a simulation ({n} settings in {len(GROUPS)} groups, plus the per-material BRDF "
        f"settings), schema version {SCHEMA_VERSION}. The same names are the keys of a config file "
        "(`[laser]`, `[receiver]`, … tables in TOML, or nested objects in JSON; `blender -c ladar export-config` "
        "writes one) and of `metadata.json`'s `settings`; in Blender they are the ladar panels' fields. Values are "
        "SI (seconds, metres, radians, joules); *in the panels* gives the label of the Blender field and the unit "
        "it shows the value in (ns, µJ, fJ, mrad, …: the add-on converts exactly, `ladar_addon/fields.py`). A value "
        "outside "
        "*allowed* is refused with a message naming the setting, the value and the allowed range.",
        "",
        "## System",
        "",
        "A config file may also set `preset = \"NAME\"` at its top level: a real-instrument preset "
        "(`core/presets/sensors/NAME.toml`, listed with its sources in [sensors.md](sensors.md)) or the path of "
        "your own preset file ending in `.toml`. Its settings are applied first, then the file's other keys over "
        "them; `export-config --preset NAME` writes the expanded settings. A preset's `[published]` table is the "
        "maker's figures, not settings. The shipped presets (`NAME`: maker and model):",
        "",
    ]
    lines += [f"- `{name}`: {load_preset(name).title}" for name in list_presets()] + [""]
    top = [f for f in dataclasses.fields(SimulationConfig) if f.name not in GROUPS and f.name != "materials"]
    lines += list(HEADER)
    for f in top:
        lines.append(row(f, f.name, f.default))
    for g in GROUPS:
        cls = type(getattr(cfg, g))
        doc = link_theory(" ".join((cls.__doc__ or "").split()))
        lines += ["", f"## `{g}`", "", doc, ""] + table(cls, f"{g}.")
    doc = link_theory(" ".join((BRDFSettings.__doc__ or "").split()))
    lines += ["", "## `materials.<name>`", "",
              "BRDF overrides by material name (`[materials.Concrete]` in TOML): a run can change a material of the "
              "scene without editing the .blend. " + doc, ""] + table(BRDFSettings, "")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="compare instead of writing")
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        if not OUT.is_file() or OUT.read_text(encoding="utf-8") != text:
            print(f"settings_reference: {OUT.relative_to(REPO)} differs from the schema; "
                  "run python scripts/settings_reference.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text, encoding="utf-8")
    print(f"settings_reference: wrote {OUT.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
