#!/usr/bin/env python3
"""Run the extension's ``ladar`` command through the ``bpy`` module (no Blender binary needed).

    python scripts/ladar_run.py scene.blend simulate --out runs/r1 [--frame N] [--seed N] [--config FILE] [--overwrite]
    python scripts/ladar_run.py scene.blend export-config --out settings.toml
    python scripts/ladar_run.py scene.blend validate-config settings.toml

It does what ``blender -b scene.blend -c ladar ...`` does: with ``BLENDER_USER_RESOURCES`` pointing at a fresh
temporary folder (set before ``import bpy``), it installs this repository as an extension in a local extension
repository, enables it as ``bl_ext.ladar_dev.ladar_simulator``, opens the .blend file and calls the command
handler the extension registers.  Exit codes: 0 success, 1 user error (one line on stderr), 2 usage error.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import blender_env  # noqa: E402

USAGE = "usage: ladar_run.py SCENE.blend {simulate,export-config,validate-config} [options]  (-h for help)"


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__ if argv else USAGE, file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    blend, command = Path(argv[0]), argv[1:]
    if blend.suffix.lower() != ".blend" or not blend.is_file():
        print(f"ladar: error: {blend} is not an existing .blend file", file=sys.stderr)
        return 1

    blender_env.isolate_user_resources()  # a temporary folder, removed at exit
    import bpy

    addon = blender_env.install_extension()
    bpy.ops.wm.open_mainfile(filepath=str(blend.resolve()), load_ui=False)
    return addon.ladar_addon.cli.cli_handler(command)


if __name__ == "__main__":
    sys.exit(main())
