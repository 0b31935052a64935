#!/usr/bin/env bash
# Set up (if needed) and run the demo: a headless 3D flash ladar simulation of the bundled sample scene,
# through the same `ladar simulate` command Blender's `-c ladar` runs. Outputs go to runs/demo-<time>/.
set -euo pipefail
cd "$(dirname "$0")/.."
LADAR_SETUP_CLIENTS=0 bash scripts/setup.sh  # (the test-only point-cloud clients are not needed for the demo)
out="runs/demo-$(date +%Y%m%d-%H%M%S)"
exec .venv/bin/python scripts/ladar_run.py sample_blends/flash_demo.blend simulate --out "$out" "$@"
