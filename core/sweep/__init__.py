"""Parameter sweeps: a validated TOML sweep file expanded into points, each point × seed × frame a task run on
Dask workers against a scene exported once (docs/sweeps.md).

    spec.py    the sweep file: format, axes, grid/zip, per-point settings validated before anything runs
    scene.py   the exported scene (geometry, materials, per-frame poses and trajectories): .npz + .json
    task.py    one task on a worker: simulate, summarise against the noise-free truth, write its run folder
    runner.py  the client: sweep folder, resume, Dask (local cluster or a scheduler), progress, results table

Import the modules themselves (``from core.sweep.runner import run_sweep``), not this package.
"""
