"""Running a frame: the table of sensor systems, and a frame into its run folder.

    run_simulation = claim the run folder → SYSTEMS[config.system_type](...) → ground truth, pose → metadata
                     → the run's files, staged, then renamed into place (fileio.staging)

Every system is one function with the same signature (paper §2)::

    system(scene, world_from_sensor, config, *, frame=0, tracer=None, trajectory=None, start_time_s=0.0,
           progress=None, cancel=None) -> FrameResult

A system that also takes ``products`` (a ``fileio.run_folder.ProductFiles``: the scanner) gets, when the frame is
written to a run folder, the means to fill its large arrays in place in their files there.

A new system is a module in ``core/systems/`` exposing such a function, and one row in :data:`SYSTEMS` (plus
its name in ``config.settings.SYSTEM_TYPES``).
"""
from __future__ import annotations

import inspect
import time
from collections.abc import Mapping

from .config.settings import SimulationConfig
from .config.validate import validate_config
from .config.files import config_to_dict
from .engine.result import FrameResult
from .errors import Cancelled, ConfigError
from .engine.products import label_points, record_pose
from .fileio.run_folder import ProductFiles, run_warnings, software_versions, write_run_files
from .fileio.staging import claim_run_dir
from .heap import release_freed_blocks
from .jit import kernel_report
from .geometry.scene import SceneGeometry
from .version import __version__


class _Systems(Mapping):
    """System type → the function that simulates one frame of it, its module imported at first use: a flash
    command does not load the scanner's and the gated viewer's modules and kernels (issue 25: start-up)."""

    NAMES = {"flash": "simulate_frame", "profiler": "simulate_profiler", "scanner": "simulate_scan",
             "gated": "simulate_gated"}

    def __getitem__(self, system_type: str):
        name = self.NAMES[system_type]  # (KeyError for an unknown type, as a dict)
        if system_type in ("flash", "profiler"):
            from .systems import flash as module
        elif system_type == "scanner":
            from .systems import scanner as module
        else:
            from .systems import gated as module
        return getattr(module, name)

    def __iter__(self):
        return iter(self.NAMES)

    def __len__(self) -> int:
        return len(self.NAMES)


#: system type → the function that simulates one frame of it: "flash" 3D flash ladar (§2.3); "profiler" range
#: profiler (§5.3), the flash model with one detector element; "scanner" time-of-flight scanner (§2.1), the sensor
#: moving along ``trajectory``; "gated" burst illumination / gated viewing (§2.2)
SYSTEMS = _Systems()


def simulate(scene: SceneGeometry, world_from_sensor, config: SimulationConfig, *, frame: int = 0, tracer=None,
             trajectory=None, start_time_s: float = 0.0, progress=None, cancel=None,
             ground_truth: bool = True, products: ProductFiles | None = None) -> FrameResult:
    """Simulate one frame of the sensor system ``config.system_type`` (:data:`SYSTEMS`), with the ground truth of
    its points (``points["material_id"]``, core/engine/products.py label_points) unless ``ground_truth`` is false
    (a caller that writes no product holding it: the stage plan records the skip).  ``products``: the run folder
    being built, for a system that fills its large arrays in their files there (module doc)."""
    validate_config(config)  # a SimulationConfig (not None or a dict) with valid settings, e.g. its system type
    system = SYSTEMS.get(config.system_type)
    if system is None:
        raise ConfigError("system_type", config.system_type, f"one of {', '.join(SYSTEMS)}")
    kernels = kernel_report()
    more = {"products": products} if products is not None and _takes_products(system) else {}
    result = system(scene, world_from_sensor, config, frame=frame, tracer=tracer, trajectory=trajectory,
                    start_time_s=start_time_s, progress=progress, cancel=cancel, **more)
    label_points(result, scene, world_from_sensor, config, needed=ground_truth)
    record_pose(result, world_from_sensor, trajectory if config.system_type == "scanner" else None)
    # compiled kernels loaded from the cache or compiled during this frame (not in the stage times)
    result.stats["kernels"] = kernel_report(kernels)
    return result


def _takes_products(system) -> bool:
    return "products" in inspect.signature(system).parameters


def run_metadata(config: SimulationConfig, result: FrameResult, frame: int, extra: dict | None = None) -> dict:
    """The run's ``metadata.json`` record (settings, seed, versions, the frame's stats and stage log)."""
    meta = {"format": "ladar-run", "format_version": 1, "simulator_version": __version__,
            "system_type": config.system_type, "frame": frame, "seed": config.run.seed,
            "settings": config_to_dict(config), "software": software_versions(),
            "created_unix_s": time.time()}
    meta.update(result.stats)
    warnings = run_warnings(result.stats)
    if warnings:
        meta["warnings"] = warnings
    if extra:
        meta.update(extra)
    return meta


def run_simulation(scene: SceneGeometry, world_from_sensor, config: SimulationConfig, out_dir, *, frame: int = 0,
                   overwrite: bool = False, extra_metadata: dict | None = None, tracer=None, progress=None,
                   cancel=None, trajectory=None, start_time_s: float = 0.0):
    """Simulate a frame of any system type and write its run folder.  Returns (run_path, FrameResult).

    Nothing is written if the settings or the scene are invalid, if the folder exists and ``overwrite`` is
    false (with ``overwrite``: if it is not a previous run of this tool), if another run is writing it, or if the
    run is cancelled.  The folder's name is claimed before the simulation starts (fileio.staging).
    """
    validate_config(config)  # a SimulationConfig (not None or a dict); before the folder is claimed
    try:
        with claim_run_dir(out_dir, if_exists="replace" if overwrite else "stop") as claim:
            result = simulate(scene, world_from_sensor, config, frame=frame, tracer=tracer, trajectory=trajectory,
                              start_time_s=start_time_s, progress=progress, cancel=cancel,
                              products=ProductFiles(claim.work))
            if cancel is not None and cancel():
                raise Cancelled()
            write_run_files(claim.work, result, run_metadata(config, result, frame, extra_metadata))
            path = claim.commit()
    finally:
        release_freed_blocks()  # the memory the run freed goes back to the system (core/heap.py)
    return path, result
