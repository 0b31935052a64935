"""Every shell command in README.md and docs/*.md is accounted for in docs/commands.toml, and is run by a test.

Commands are taken from fenced ``bash``/``sh``/``shell``/``console`` blocks (one per logical line, ``\\``
continuations joined, comments dropped), from untagged fenced blocks (lines that start with a command, indented
lines continuing them) and from inline code that starts with a command (``.venv/bin/python …``, ``bash …``,
``blender …``, ``pip …``, ``dask …``, or a ``scripts/…`` file followed by arguments).  docs/commands.toml holds one
entry per command, with exactly one of:

* ``run``: a quick variant of the command that this file runs itself, outputs in a temporary folder (``{tmp}``);
* ``test``: the test that runs it (or its quick form): ``path::function`` or ``path::function[id]``, checked to
  exist;
* ``not_runnable``: why it cannot run here (a Blender binary, other machines, the network, a usage synopsis),
  with ``test`` naming the test that runs its equivalent (for ``blender -b …``: the same ``ladar`` handler
  through the bpy module, which is what ``scripts/ladar_run.py`` runs).

A command added to the docs without an entry fails :func:`test_every_documented_command_has_an_entry`; an entry
whose command left the docs fails it too.  The ``run`` variants leave every committed file unchanged
(:func:`test_the_runs_left_the_committed_files_alone`).
"""
from __future__ import annotations

import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MAPPING = REPO / "docs" / "commands.toml"
FENCE = re.compile(r"^```([\w-]*)[^\n]*\n(.*?)^```", re.S | re.M)
SHELL_LANGS = {"bash", "sh", "shell", "console"}
#: first words that make a line or an inline code span a command
PROGRAMS = (".venv/bin/python", "python", "python3", "python3.11", "bash", "sh", "blender", "pip", "pip3", "dask")
SCRIPT_WITH_ARGS = re.compile(r"^(scripts|bench)/[\w./-]+\.(py|sh)\s+\S")


def _normalise(cmd: str) -> str:
    return " ".join(cmd.split())


def _is_command(text: str) -> bool:
    words = text.split()
    if not words:
        return False
    first = words[0]
    return (first in PROGRAMS and len(words) > 1 or re.match(r"^~/[\w.-]+/bin/\w", first) is not None
            or SCRIPT_WITH_ARGS.match(text) is not None)


def _strip_comment(line: str) -> str:
    return re.split(r"\s+#\s", line, maxsplit=1)[0].rstrip() if not line.lstrip().startswith("#") else ""


def _shell_block(body: str) -> list[str]:
    out, pending = [], ""
    for raw in body.splitlines():
        line = pending + _strip_comment(raw).strip() if pending else _strip_comment(raw).strip()
        if line.endswith("\\"):
            pending = line[:-1] + " "
            continue
        pending = ""
        line = line[2:] if line.startswith("$ ") else line  # a console prompt
        if line and not line.startswith("#"):
            out.append(_normalise(line))
    return out


def _plain_block(body: str) -> list[str]:
    out = []
    for raw in body.splitlines():
        if out and raw[:1].isspace() and raw.strip() and current:
            out[-1] = _normalise(out[-1] + " " + _strip_comment(raw))
            continue
        line = _strip_comment(raw).strip()
        current = _is_command(line)
        if current:
            out.append(_normalise(line))
    return out


def documented_commands() -> dict[str, list[str]]:
    """command → the documents it appears in."""
    found: dict[str, list[str]] = {}
    for doc in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        text = doc.read_text(encoding="utf-8")
        name = doc.relative_to(REPO).as_posix()
        cmds = []
        for m in FENCE.finditer(text):
            lang, body = m.group(1).lower(), m.group(2)
            if lang in SHELL_LANGS:
                cmds += _shell_block(body)
            elif lang == "":
                cmds += _plain_block(body)
        prose = FENCE.sub("", text)
        cmds += [_normalise(span) for span in re.findall(r"`([^`\n]+)`", prose) if _is_command(span.strip())]
        for c in cmds:
            found.setdefault(c, [])
            if name not in found[c]:
                found[c].append(name)
    return found


def entries() -> list[dict]:
    return tomllib.loads(MAPPING.read_text(encoding="utf-8"))["command"]


def _runs() -> list[dict]:
    return [e for e in entries() if "run" in e]


def test_the_extractor_finds_commands_in_each_form():
    text = ("```bash\n.venv/bin/python a.py \\\n    --out runs/x   # note\n# comment\n```\n"
            "```\nblender -b s.blend -c ladar simulate [--out DIR]\n        [--seed N]\nladar: error: no\n```\n")
    assert _shell_block(FENCE.search(text).group(2)) == [".venv/bin/python a.py --out runs/x"]
    assert _shell_block("$ bash scripts/demo.sh\n") == ["bash scripts/demo.sh"]
    assert _plain_block(list(FENCE.finditer(text))[1].group(2)) == [
        "blender -b s.blend -c ladar simulate [--out DIR] [--seed N]"]
    assert _is_command("scripts/sweep_plots.py DIR") and not _is_command("scripts/sweep_plots.py")
    assert _is_command("~/ladar-worker/bin/dask scheduler --port 8786") and not _is_command("--quick")


def test_every_documented_command_has_an_entry():
    documented = documented_commands()
    listed = [_normalise(e["command"]) for e in entries()]
    assert len(listed) == len(set(listed)), "a command is listed twice in docs/commands.toml"
    missing = [f"{c!r} (in {', '.join(documented[c])})" for c in documented if c not in listed]
    stale = [c for c in listed if c not in documented]
    assert not missing, ("documented commands without an entry in docs/commands.toml (add one: a quick `run`, the "
                         "`test` that runs it, or `not_runnable` with its reason):\n" + "\n".join(missing))
    assert not stale, "docs/commands.toml lists commands no document has any more:\n" + "\n".join(stale)


def test_every_entry_says_how_it_is_run():
    run_ids = {e["id"] for e in _runs()}
    assert len(run_ids) == len(_runs()), "every `run` entry needs its own `id`"
    for e in entries():
        kinds = [k for k in ("run", "test", "not_runnable") if k in e]
        assert kinds, f"{e['command']!r}: needs `run`, `test` or `not_runnable`"
        assert not ("run" in e and "not_runnable" in e), f"{e['command']!r}: `run` or `not_runnable`, not both"
        if "not_runnable" in e:
            assert len(e["not_runnable"]) > 10, f"{e['command']!r}: say why it cannot run here"
        for ref in ([e["test"]] if isinstance(e.get("test"), str) else e.get("test", [])):
            path, _, func = ref.partition("::")
            func, _, param = func.partition("[")
            source = (REPO / path).read_text(encoding="utf-8") if (REPO / path).is_file() else ""
            assert f"def {func}(" in source, f"{e['command']!r}: no test {ref}"
            if param:
                case = param.rstrip("]")
                assert f'"{case}"' in source or (func == "test_documented_command_runs" and case in run_ids), \
                    f"{e['command']!r}: no case {case} in {path}"
        if "run" in e:
            assert "{tmp}" in e["run"] or e.get("writes_nothing"), f"{e['run']!r}: outputs go to {{tmp}}"


@pytest.fixture(scope="module")
def git_before():
    if not (REPO / ".git").exists():
        pytest.skip("not a git checkout")
    from test_bench_quick import committed_state
    return committed_state()


@pytest.mark.parametrize("entry", [pytest.param(e, id=e["id"], marks=[pytest.mark.slow] if e.get("slow") else [])
                                   for e in _runs()])
def test_documented_command_runs(entry, tmp_path, git_before):
    argv = shlex.split(entry["run"].replace("{tmp}", str(tmp_path)))
    if argv[0] == ".venv/bin/python":
        argv[0] = sys.executable
    proc = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=entry.get("timeout_s", 300))
    assert proc.returncode == 0, f"{entry['run']}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    for rel in entry.get("creates", []):
        assert (tmp_path / rel).exists(), f"{entry['run']}: no {rel} in the output folder"


def test_the_runs_left_the_committed_files_alone(git_before):
    from test_bench_quick import committed_state
    assert committed_state() == git_before
