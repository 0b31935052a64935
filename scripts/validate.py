#!/usr/bin/env python3
"""Write the validation report: one page per effect (plots + a table of checks against theory or an independent
reference) and a summary of every check.

    .venv/bin/python scripts/validate.py --out DIR [--quick] [--only EFFECT[,EFFECT…]]
    .venv/bin/python scripts/validate.py --update-committed [--only EFFECT[,EFFECT…]]

The effects are the modules of scripts/validation/ (found automatically; their interface is documented in
scripts/validation/__init__.py).  DIR receives summary.md, checks.json, <effect>.md and <effect>/*.png.
``--update-committed`` regenerates the committed report in docs/validation/ (the only way this script writes
there; never with --quick).  A full run also runs every effect in quick mode and records those values in
checks.json (``quick_simulated``), so tests/test_validation_report.py can compare a quick run with the committed
report.  ``--only`` runs the named effects and keeps the others' results already in DIR/checks.json.
An effect whose optional environment is missing (its ``run`` raises ``validation.Skipped``) is listed as skipped
with the reason; its results already in DIR/checks.json (and its page and plots) are kept, never overwritten by
the skip.
Exit status 0 when every check passed, 1 otherwise, 2 on bad arguments.
"""
from __future__ import annotations

import argparse
import importlib
import json
import math
import pkgutil
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"
COMMITTED = ROOT / "docs" / "validation"
for p in (str(ROOT), str(SCRIPTS)):
    if p not in sys.path:
        sys.path.insert(0, p)

import matplotlib  # noqa: E402

matplotlib.use("Agg")

import validation  # noqa: E402
from validation import KINDS, Skipped, within  # noqa: E402

#: Effects of issue 32 that have no module yet, and why (listed on the summary page until a module exists).
NOT_YET: dict = {}


def discover() -> list[str]:
    """Names of the effect modules in scripts/validation/ (not starting with ``_``)."""
    return sorted(m.name for m in pkgutil.iter_modules(validation.__path__)
                  if not m.name.startswith("_") and not m.ispkg)


def load(name: str):
    return importlib.import_module(f"validation.{name}")


def order_key(name: str, modules: dict):
    mod = modules.get(name)
    return (getattr(mod, "ORDER", 100) if mod is not None else 100, name)


def normalise(effect: str, raw, seen: set) -> dict:
    """A module's check as a plain JSON-able dict; ValueError naming the effect, field and value when malformed."""
    if not isinstance(raw, dict):
        raise ValueError(f"{effect}: a check must be a dict, got {type(raw).__name__}")
    for field in ("quantity", "simulated", "reference", "tolerance"):
        if field not in raw:
            raise ValueError(f"{effect}: check {raw.get('quantity', '?')!r} has no field {field!r}")
    q = str(raw["quantity"])
    if q in seen:
        raise ValueError(f"{effect}: quantity {q!r} appears twice (quantities identify checks)")
    seen.add(q)
    kind = raw.get("kind", "rel")
    if kind not in KINDS:
        raise ValueError(f"{effect}: check {q!r} kind = {kind!r}: allowed {', '.join(KINDS)}")
    sim, ref, tol = float(raw["simulated"]), float(raw["reference"]), float(raw["tolerance"])
    if not tol >= 0:
        raise ValueError(f"{effect}: check {q!r} tolerance = {tol}: allowed ≥ 0")
    passed = bool(raw["passed"]) if "passed" in raw else within(sim, ref, tol, kind)
    return {"quantity": q, "simulated": sim if math.isfinite(sim) else None, "reference": ref, "tolerance": tol,
            "kind": kind, "passed": passed, "unit": str(raw.get("unit", "")), "note": str(raw.get("note", ""))}


def run_effect(name: str, out_dir: Path, quick: bool) -> tuple[list, float, str | None]:
    """Runs one effect into ``out_dir``; returns (checks, seconds, error text or None).  An effect that cannot run
    here raises :class:`validation.Skipped` through this function."""
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:
        mod = load(name)
        if not callable(getattr(mod, "run", None)):
            raise TypeError(f"scripts/validation/{name}.py has no run(out_dir, quick) function")
        raw = mod.run(out_dir, quick)
        seen: set = set()
        checks = [normalise(name, c, seen) for c in (raw or [])]
        if not checks:
            raise ValueError(f"{name}: run() returned no checks")
        return checks, time.perf_counter() - t0, None
    except Skipped:
        raise
    except Exception as exc:  # one broken effect must not hide the others
        tb = traceback.format_exc()
        print(tb, file=sys.stderr)
        err = f"{type(exc).__name__}: {exc}".splitlines()[0]
        return ([{"quantity": "effect module ran", "simulated": None, "reference": 1.0, "tolerance": 0.0,
                  "kind": "abs", "passed": False, "unit": "", "note": err}], time.perf_counter() - t0, err)


def fmt(x) -> str:
    if x is None:
        return "—"
    if isinstance(x, bool):
        return str(x)
    x = float(x)
    if x == 0:
        return "0"
    if 1e-3 <= abs(x) < 1e5:
        return f"{x:.6g}"
    return f"{x:.4e}"


def tol_text(c: dict) -> str:
    t = fmt(c["tolerance"])
    return {"rel": f"±{c['tolerance'] * 100:.3g} %", "abs": f"±{t}", "max": f"≤ ref + {t}",
            "min": f"≥ ref − {t}"}[c["kind"]]


def table(checks: list, link: str | None = None) -> list[str]:
    head = "| quantity | simulated | reference | tolerance | result |" if link is None else \
        "| effect | quantity | simulated | reference | tolerance | result |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for c in checks:
        unit = f" [{c['unit']}]" if c.get("unit") else ""
        note = f" ({c['note']})" if c.get("note") else ""
        cells = [f"{c['quantity']}{unit}{note}", fmt(c["simulated"]), fmt(c["reference"]), tol_text(c),
                 "pass" if c["passed"] else "**FAIL**"]
        if link is not None:
            cells.insert(0, link)
        lines.append("| " + " | ".join(s.replace("|", "\\|") for s in cells) + " |")
    return lines


def _page_head(name: str, mod) -> list[str]:
    """An effect page's first lines: its title and its module's introduction (if any)."""
    lines = [f"# {getattr(mod, 'TITLE', name) if mod is not None else name}", ""]
    intro = getattr(mod, "INTRO", "") if mod is not None else ""
    return lines + ([intro.strip(), ""] if intro else [])


def write_page(out: Path, name: str, mod, entry: dict) -> None:
    lines = _page_head(name, mod)
    n_pass = sum(c["passed"] for c in entry["checks"])
    lines += [f"{n_pass} of {len(entry['checks'])} checks pass ({entry['mode']} run, {entry['seconds']:.0f} s).  "
              "Generated by `scripts/validate.py`; the summary of every effect is [summary.md](summary.md).", ""]
    if entry.get("error"):
        lines += [f"**The effect module failed:** `{entry['error']}`", ""]
    lines += table(entry["checks"]) + [""]
    folder = out / name
    for md in sorted(folder.glob("*.md")):
        lines += [f"More detail: [{name}/{md.name}]({name}/{md.name}).", ""]
    for png in sorted(folder.glob("*.png")):
        lines += [f"![{png.stem}]({name}/{png.name})", ""]
    (out / f"{name}.md").write_text("\n".join(lines), encoding="utf-8")


def write_skipped_page(out: Path, name: str, mod, reason: str) -> None:
    lines = _page_head(name, mod)
    lines += [f"**Skipped on this machine:** {reason}", ""]
    (out / f"{name}.md").write_text("\n".join(lines), encoding="utf-8")


def write_summary(out: Path, data: dict, modules: dict) -> None:
    skipped = {n: e["skipped"] for n, e in data["effects"].items() if e.get("skipped") and not e["checks"]}
    effects = sorted((n for n in data["effects"] if n not in skipped), key=lambda n: order_key(n, modules))
    allc = [c for n in effects for c in data["effects"][n]["checks"]]
    n_pass = sum(c["passed"] for c in allc)
    lines = ["# Validation report: summary", "",
             f"{n_pass} of {len(allc)} checks pass over {len(effects)} effects.  Every number below is produced by "
             "`scripts/validate.py` from the code as it is (a test, tests/test_validation_report.py, reruns the "
             "quick mode and compares it with this report).  Tolerance `±x %` is relative to the reference.", "",
             "| effect | checks | passed | mode | time [s] |", "|---|---|---|---|---|"]
    for n in effects:
        e = data["effects"][n]
        title = getattr(modules.get(n), "TITLE", n)
        lines.append(f"| [{title}]({n}.md) | {len(e['checks'])} | {sum(c['passed'] for c in e['checks'])} | "
                     f"{e['mode']} | {e['seconds']:.0f} |")
    failing = [(n, c) for n in effects for c in data["effects"][n]["checks"] if not c["passed"]]
    if failing:
        lines += ["", "## Failing checks", ""]
        lines += ["| effect | quantity | simulated | reference | tolerance |", "|---|---|---|---|---|"]
        lines += [f"| [{n}]({n}.md) | {c['quantity']} | {fmt(c['simulated'])} | {fmt(c['reference'])} | "
                  f"{tol_text(c)} |" for n, c in failing]
    kept = {n: e["skipped"] for n, e in data["effects"].items() if e.get("skipped") and e["checks"]}
    if skipped or kept:
        lines += ["", "## Skipped on this machine", ""]
        lines += [f"- **{n}** (no results): {r}" for n, r in sorted(skipped.items())]
        lines += [f"- **{n}** (the results above are from an earlier run where it could run): {r}"
                  for n, r in sorted(kept.items())]
    missing = {k: v for k, v in NOT_YET.items() if k not in data["effects"]}
    if missing:
        lines += ["", "## Not validated yet", ""] + [f"- **{k}**: {v}" for k, v in missing.items()]
    lines += ["", "## Every check", ""]
    for n in effects:
        lines += table(data["effects"][n]["checks"], link=f"[{n}]({n}.md)")[(0 if n == effects[0] else 2):]
    lines.append("")
    (out / "summary.md").write_text("\n".join(lines), encoding="utf-8")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="folder for the report (not the committed docs/validation/)")
    ap.add_argument("--update-committed", action="store_true", help="regenerate docs/validation/ (full run)")
    ap.add_argument("--quick", action="store_true", help="small run (about a minute; never committed)")
    ap.add_argument("--only", default="", help="comma-separated effects to run (default: all)")
    args = ap.parse_args(argv)
    available = discover()
    if args.update_committed:
        if args.out is not None:
            ap.error(f"--out = {args.out} and --update-committed: choose one")
        if args.quick:
            ap.error("--quick and --update-committed: a quick run's report is never committed")
        out = COMMITTED
    elif args.out is None:
        ap.error("--out DIR is required (or --update-committed)")
    else:
        out = args.out
        try:
            out.resolve().relative_to(COMMITTED.resolve())
            ap.error(f"--out = {args.out} is the committed report: use --update-committed to regenerate it")
        except ValueError:
            pass
    chosen = [s.strip() for s in args.only.split(",") if s.strip()] or available
    bad = [s for s in chosen if s not in available]
    if bad:
        ap.error(f"--only = {','.join(bad)}: allowed effects {', '.join(available)}")

    out.mkdir(parents=True, exist_ok=True)
    data = {"effects": {}}
    old = out / "checks.json"
    previous = json.loads(old.read_text(encoding="utf-8")).get("effects", {}) if old.exists() else {}
    if args.only:
        data["effects"] = {k: v for k, v in previous.items() if k in available}
    modules = {}
    for n in available:
        try:
            modules[n] = load(n)
        except Exception:
            modules[n] = None
    t_all = time.perf_counter()
    for name in chosen:
        print(f"[validate] {name} ({'quick' if args.quick else 'full'}) …", flush=True)
        with tempfile.TemporaryDirectory(prefix=f"validate-{name}-") as tmp:
            stage = Path(tmp) / name  # staged: a failing run leaves the previous plots in place
            try:
                checks, secs, err = run_effect(name, stage, args.quick)
            except Skipped as exc:
                reason = str(exc)
                print(f"[validate] {name}: skipped: {reason}", flush=True)
                if previous.get(name, {}).get("checks"):  # keep the results (page, plots) of a run that could
                    data["effects"][name] = {**previous[name], "skipped": reason}
                else:
                    data["effects"][name] = {"mode": "skipped", "seconds": 0.0, "error": None, "skipped": reason,
                                             "checks": []}
                    write_skipped_page(out, name, modules.get(name), reason)
                continue
            if args.quick:
                for c in checks:
                    c["quick_simulated"] = c["simulated"]
            else:
                qchecks, qsecs, _ = run_effect(name, Path(tmp) / "quick", True)
                qmap = {c["quantity"]: c["simulated"] for c in qchecks}
                for c in checks:
                    c["quick_simulated"] = qmap.get(c["quantity"])
            target = out / name
            if target.exists():
                shutil.rmtree(target)
            shutil.copytree(stage, target)
        data["effects"][name] = {"mode": "quick" if args.quick else "full", "seconds": round(secs, 1),
                                 "error": err, "checks": checks}
        write_page(out, name, modules.get(name), data["effects"][name])
        n_pass = sum(c["passed"] for c in checks)
        print(f"[validate] {name}: {n_pass}/{len(checks)} pass, {secs:.1f} s", flush=True)
    (out / "checks.json").write_text(json.dumps(data, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    write_summary(out, data, modules)
    allc = [c for e in data["effects"].values() if not e.get("skipped") for c in e["checks"]]
    n_fail = sum(not c["passed"] for c in allc)
    print(f"[validate] {len(allc) - n_fail}/{len(allc)} checks pass, {time.perf_counter() - t_all:.0f} s; "
          f"report in {out}/summary.md", flush=True)
    return 0 if n_fail == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
