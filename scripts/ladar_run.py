#!/usr/bin/env python3
"""Run the extension's ``ladar`` command through the ``bpy`` module (no Blender binary needed).

    python scripts/ladar_run.py scene.blend simulate [--out RUN_DIR] [--frame N | --frames 1-100[:STEP]]
                                [--seed N] [--config FILE] [--overwrite | --if-exists {stop,replace,new}]
                                [--sensor NAME] [--clouds {run,frame}] [--no-import] [--no-previews]
    python scripts/ladar_run.py scene.blend export-config --out settings.toml
    python scripts/ladar_run.py scene.blend validate-config settings.toml
    python scripts/ladar_run.py scene.blend simulate --help      (the command's full help)

It does what ``blender -b scene.blend -c ladar ...`` does: with ``BLENDER_USER_RESOURCES`` pointing at a fresh
temporary folder (set before ``import bpy``), it installs this repository as an extension in a local extension
repository, enables it as ``bl_ext.ladar_dev.ladar_simulator``, opens the .blend file and calls the command
handler the extension registers.  Exit codes: 0 success, 1 user error (one line on stderr), 2 usage error,
130 interrupted (Ctrl-C: nothing of the run is left behind).
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import blender_env  # noqa: E402

USAGE = ("usage: ladar_run.py SCENE.blend {simulate,export-config,validate-config} [options]\n"
         "       (ladar_run.py -h: this script; ladar_run.py SCENE.blend simulate -h: the command's options)")


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__ if argv else USAGE, file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    blend, command = Path(argv[0]), argv[1:]
    if blend.suffix.lower() != ".blend" or not blend.is_file():
        print(f"ladar: error: {blend} is not an existing .blend file", file=sys.stderr)
        return 1

    try:
        blender_env.isolate_user_resources()  # a temporary folder, removed at exit
        import bpy

        addon = blender_env.install_extension()
        bpy.ops.wm.open_mainfile(filepath=str(blend.resolve()), load_ui=False)
        return addon.ladar_addon.cli.cli_handler(command)
    except KeyboardInterrupt:
        print("ladar: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
