"""The validation report (scripts/validate.py, docs/validation/) holds the numbers the code produces today.

The quick mode runs every effect module of scripts/validation/ into a temporary folder; the committed report
(docs/validation/checks.json, written by ``scripts/validate.py --update-committed``) records beside each full-run
value the value of the same check in quick mode.  A quick value that moved from the committed one by more than the
check's own tolerance (read with its kind: relative to the reference, absolute, or a one-sided margin) fails here:
the code changed what the report says, and the report must be regenerated (and read).  A check the quick run
makes that the report lacks, or the reverse, fails as well; so does a failing quick check or a page or plot missing.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
COMMITTED = REPO / "docs" / "validation"
sys.path.insert(0, str(REPO / "scripts"))

from validation import allowed_difference, check, save  # noqa: E402


def _runner():
    """scripts/validate.py as a module (by path: another ``validate`` module may be imported already)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("validation_runner", REPO / "scripts" / "validate.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("validation")
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "validate.py"), "--out", str(out), "--quick"],
                          cwd=REPO, capture_output=True, text=True, timeout=900)
    assert (out / "checks.json").exists(), proc.stdout[-3000:] + proc.stderr[-3000:]
    return out, proc, json.loads((out / "checks.json").read_text(encoding="utf-8"))


@pytest.mark.slow
def test_quick_report_agrees_with_the_committed_report(quick_report):
    out, proc, now = quick_report
    committed = json.loads((COMMITTED / "checks.json").read_text(encoding="utf-8"))
    assert sorted(now["effects"]) == sorted(committed["effects"]), "effects added or removed: regenerate the report"
    problems = []
    for effect, entry in now["effects"].items():
        assert entry["error"] is None, f"{effect}: {entry['error']}"
        if entry.get("skipped"):  # an optional environment is missing here (the reason is on the summary page)
            print(f"{effect}: skipped on this machine: {entry['skipped']}")
            continue
        old = {c["quantity"]: c for c in committed["effects"][effect]["checks"]}
        quick_in_old = {q for q, c in old.items() if c.get("quick_simulated") is not None}
        new = {c["quantity"]: c for c in entry["checks"]}
        for q in sorted(set(new) - quick_in_old):
            problems.append(f"{effect}: quick check {q!r} is not in the committed report")
        for q in sorted(quick_in_old - set(new)):
            problems.append(f"{effect}: committed check {q!r} is no longer made by the quick run")
        for q in sorted(set(new) & quick_in_old):
            c = new[q]
            was = old[q]["quick_simulated"]
            allowed = max(allowed_difference(c["reference"], c["tolerance"], c["kind"]), 1e-9 * max(1.0, abs(was)))
            if c["simulated"] is None or abs(c["simulated"] - was) > allowed:
                problems.append(f"{effect}: {q!r} is {c['simulated']} now, {was} in the committed report "
                                f"(allowed difference {allowed:.3g})")
            if not c["passed"]:
                problems.append(f"{effect}: quick check {q!r} fails: {c['simulated']} vs {c['reference']} "
                                f"({c['kind']} tolerance {c['tolerance']})")
    assert not problems, "\n".join(problems)
    assert proc.returncode == 0, proc.stdout[-2000:]


@pytest.mark.slow
def test_pages_and_plots_exist(quick_report):
    out, _, now = quick_report
    for folder in (out, COMMITTED):
        summary = (folder / "summary.md").read_text(encoding="utf-8")
        entries = json.loads((folder / "checks.json").read_text(encoding="utf-8"))["effects"]
        for effect in now["effects"]:
            page = (folder / f"{effect}.md").read_text(encoding="utf-8")
            if entries[effect].get("skipped") and not entries[effect]["checks"]:
                assert f"**{effect}** (no results): {entries[effect]['skipped']}" in summary
                assert entries[effect]["skipped"] in page
                continue
            assert f"]({effect}.md)" in summary
            pngs = sorted((folder / effect).glob("*.png"))
            assert pngs, f"{folder}/{effect}/ has no plot"
            for png in pngs:
                assert f"({effect}/{png.name})" in page
    assert "../shared" not in (COMMITTED / "summary.md").read_text(encoding="utf-8")


def test_check_helper_and_bad_checks():
    c = check("x", 1.01, 1.0, 0.02)
    assert c["passed"] and c["kind"] == "rel"
    assert not check("x", 1.03, 1.0, 0.02)["passed"]
    assert check("x", 0.5, 0.0, 1.0, kind="max")["passed"] and not check("x", 1.5, 0.0, 1.0, kind="max")["passed"]
    assert not check("x", float("nan"), 1.0, 1.0)["passed"]
    assert allowed_difference(2.0, 0.1, "rel") == pytest.approx(0.2)
    assert allowed_difference(2.0, 0.1, "abs") == pytest.approx(0.1)
    with pytest.raises(ValueError, match="kind = 'relative'"):
        check("x", 1.0, 1.0, 0.1, kind="relative")
    with pytest.raises(ValueError, match="tolerance = -1"):
        check("x", 1.0, 1.0, -1)
    validate = _runner()
    with pytest.raises(ValueError, match="weather: check 'a' has no field 'reference'"):
        validate.normalise("weather", {"quantity": "a", "simulated": 1.0, "tolerance": 0.1}, set())
    with pytest.raises(ValueError, match="quantity 'a' appears twice"):
        seen = set()
        validate.normalise("weather", {"quantity": "a", "simulated": 1, "reference": 1, "tolerance": 0}, seen)
        validate.normalise("weather", {"quantity": "a", "simulated": 1, "reference": 1, "tolerance": 0}, seen)


def test_a_plot_without_a_legend_is_refused(tmp_path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    ax.set(title="t", xlabel="x [m]", ylabel="y [m]")
    with pytest.raises(ValueError, match="missing legend"):
        save(fig, tmp_path / "a.png")
    assert not (tmp_path / "a.png").exists()


def test_a_broken_effect_module_is_reported_and_the_others_still_run(tmp_path, monkeypatch):
    validate = _runner()
    monkeypatch.setattr(validate, "load", lambda name: (_ for _ in ()).throw(ImportError("no module " + name)))
    checks, _, err = validate.run_effect("weather", tmp_path / "weather", quick=True)
    assert err == "ImportError: no module weather"
    assert len(checks) == 1 and checks[0]["passed"] is False and checks[0]["quantity"] == "effect module ran"


def test_a_skipped_effect_is_listed_with_its_reason_and_keeps_earlier_results(tmp_path, monkeypatch):
    """An effect whose optional environment is missing raises validation.Skipped: the run lists it with the
    reason, counts none of its checks, and keeps the results an earlier run in the same folder recorded."""
    validate = _runner()
    import types
    from validation import Skipped

    calls = {"n": 0}

    def run(out_dir, quick):
        calls["n"] += 1
        if calls["n"] == 1:
            (out_dir / "a.png").write_bytes(b"png")
            return [check("x", 1.0, 1.0, 0.1)]
        raise Skipped("the optional environment .venv-x is missing")

    fake = types.SimpleNamespace(run=run, TITLE="Fake effect")
    monkeypatch.setattr(validate, "discover", lambda: ["fake"])
    monkeypatch.setattr(validate, "load", lambda name: fake)
    out = tmp_path / "report"
    assert validate.main(["--out", str(out), "--quick"]) == 0
    first = json.loads((out / "checks.json").read_text(encoding="utf-8"))["effects"]["fake"]
    assert first["checks"][0]["passed"] and not first.get("skipped")
    assert validate.main(["--out", str(out), "--quick", "--only", "fake"]) == 0
    kept = json.loads((out / "checks.json").read_text(encoding="utf-8"))["effects"]["fake"]
    assert kept["checks"] == first["checks"] and kept["skipped"] == "the optional environment .venv-x is missing"
    assert (out / "fake" / "a.png").exists()
    summary = (out / "summary.md").read_text(encoding="utf-8")
    assert "**fake** (the results above are from an earlier run where it could run): the optional environment" \
        in summary
    fresh = tmp_path / "fresh"
    assert validate.main(["--out", str(fresh), "--quick"]) == 0
    entry = json.loads((fresh / "checks.json").read_text(encoding="utf-8"))["effects"]["fake"]
    assert entry["checks"] == [] and entry["mode"] == "skipped"
    assert "0 of 0 checks pass over 0 effects" in (fresh / "summary.md").read_text(encoding="utf-8")
    assert "**fake** (no results): the optional environment .venv-x is missing" in \
        (fresh / "summary.md").read_text(encoding="utf-8")
    assert "Skipped on this machine:** the optional environment" in (fresh / "fake.md").read_text(encoding="utf-8")


def test_validate_atmosphere_smallest_is_the_report_quick_level(tmp_path, monkeypatch, capsys):
    """``scripts/validate_atmosphere.py --quick --smallest`` (docs/commands.toml's quick form of the documented
    command: ≈ 10 s of CPU instead of ≈ 22 s for ``--quick``) computes what the validation report's atmosphere
    effect does in quick mode (scripts/validation/atmosphere.py: ``report(…, quick=True, smallest=True)``);
    ``--smallest`` without ``--quick`` is refused."""
    import validate_atmosphere

    calls = []
    monkeypatch.setattr(validate_atmosphere, "report",
                        lambda out, quick=False, seed=20240601, smallest=False: calls.append((quick, smallest))
                        or ([], []))
    assert validate_atmosphere.main([str(tmp_path / "a"), "--quick", "--smallest"]) == 0
    assert validate_atmosphere.main([str(tmp_path / "b"), "--quick"]) == 0
    assert calls == [(True, True), (True, False)]
    with pytest.raises(SystemExit) as exit_:
        validate_atmosphere.main([str(tmp_path / "c"), "--smallest"])
    assert exit_.value.code == 2 and "--smallest goes with --quick" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()
    from validation import atmosphere as effect  # the report's quick run asks for the same level

    assert effect.run(tmp_path / "d", quick=True) == [] and calls[-1] == (True, True)
