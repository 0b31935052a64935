"""Ladar simulator core: NumPy/SciPy/embreex, never Blender.  See ../docs/architecture.md and the paper's Figure 4.

Layers, bottom to top (a module imports only from its own layer or below):
``constants``, ``errors``, ``version`` → ``config`` → ``geometry``, ``atmosphere`` → ``physics`` → ``engine``
→ ``systems``, ``fileio`` → ``sequence``.

Modules moved in the layered layout keep their old import path for now (``core.pipeline``, ``core.receiver``,
...): the finder below maps each old name to its new module and emits a ``DeprecationWarning`` naming it.
Import from the new path.  Nothing inside the simulator imports through this package namespace.
"""
import importlib
import importlib.abc
import importlib.util
import sys
import warnings

from .version import __version__

#: old module (relative to this package) -> its new home
MOVED_MODULES = {
    "scene": "geometry.scene", "trace": "geometry.trace", "culling": "geometry.culling",
    "motion": "geometry.motion", "rays": "geometry.rays",
    "propagation": "physics.propagation", "laser": "physics.laser", "brdf": "physics.brdf",
    "radiometry": "physics.radiometry", "waveform": "physics.waveform", "sampling": "physics.sampling",
    "echoes": "physics.detection.peaks", "echoes_noisy": "physics.detection.noisy",
    "receiver": "physics.receiver", "speckle": "physics.receiver.speckle",
    "memory": "engine.memory",
    "pipeline": "systems.flash", "scanner": "systems.scanner", "gated": "systems.gated",
    "runio": "fileio.run_folder", "las": "fileio.las", "preview": "fileio.preview",
}


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Resolves ``<this package>.<old name>`` to the module's new home (the same module object)."""

    def __init__(self, package: str):
        self.package = package
        self.moved_modules_of = package
        self._specs = {}

    def find_spec(self, fullname, path=None, target=None):
        head, _, old = fullname.rpartition(".")
        if head != self.package or old not in MOVED_MODULES:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        old = spec.name.rpartition(".")[2]
        new = f"{self.package}.{MOVED_MODULES[old]}"
        warnings.warn(f"{spec.name} has moved to {new}: import it from there", DeprecationWarning, stacklevel=2)
        module = importlib.import_module(new)
        self._specs[spec.name] = module.__spec__
        return module

    def exec_module(self, module):
        # the import system has just set the alias spec on the module: it keeps its own
        module.__spec__ = self._specs.pop(module.__spec__.name)


# one finder per copy of the package (the add-on installs its own copy as bl_ext.<repo>.ladar_simulator.core);
# a reload of this package replaces its finder
sys.meta_path[:] = [f for f in sys.meta_path if getattr(f, "moved_modules_of", None) != __name__]
sys.meta_path.append(_MovedModuleFinder(__name__))
