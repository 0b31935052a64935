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
import types
import warnings

from .version import __version__

#: old module (relative to this package) -> its new home, or the homes of its parts when it was split
MOVED_MODULES = {
    "scene": "geometry.scene", "trace": "geometry.trace", "culling": "geometry.culling",
    "motion": "geometry.motion", "rays": "geometry.rays",
    "propagation": ("physics.propagation", "engine.atmosphere_stage", "engine.rng"),
    "laser": "physics.laser", "brdf": ("physics.brdf", "fileio.preview"),
    "radiometry": "physics.radiometry", "waveform": "physics.waveform", "sampling": "physics.sampling",
    "echoes": "physics.detection.peaks", "echoes_noisy": "physics.detection.noisy",
    "receiver": "physics.receiver", "speckle": "physics.receiver.speckle",
    "memory": "engine.memory",
    "pipeline": ("systems.flash", "run", "engine.result", "engine.products", "engine.blocks", "errors"),
    "scanner": ("systems.scanner", "systems.scan_patterns", "config.derived"),
    "gated": "systems.gated",
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
        homes = MOVED_MODULES[old]
        if isinstance(homes, str):  # moved whole: the very same module object
            new = f"{self.package}.{homes}"
            warnings.warn(f"{spec.name} has moved to {new}: import it from there", DeprecationWarning, stacklevel=2)
            module = importlib.import_module(new)
            self._specs[spec.name] = module.__spec__
            return module
        # split: a namespace that finds each name in the module that now holds it (and says which)
        parts = [f"{self.package}.{h}" for h in homes]
        warnings.warn(f"{spec.name} was split into {', '.join(parts)}: import from those", DeprecationWarning,
                      stacklevel=2)
        module = types.ModuleType(spec.name, f"Old path of {', '.join(parts)} (deprecated).")

        def __getattr__(name, _parts=parts, _old=spec.name):
            for part in _parts:
                mod = importlib.import_module(part)
                if hasattr(mod, name) and not name.startswith("__"):
                    return getattr(mod, name)
            raise AttributeError(f"module {_old!r} has no attribute {name!r}")

        module.__getattr__ = __getattr__
        return module

    def exec_module(self, module):
        # a moved module: the import system has just set the alias spec on it; it keeps its own
        if module.__spec__.name in self._specs:
            module.__spec__ = self._specs.pop(module.__spec__.name)


# one finder per copy of the package (the add-on installs its own copy as bl_ext.<repo>.ladar_simulator.core);
# a reload of this package replaces its finder
sys.meta_path[:] = [f for f in sys.meta_path if getattr(f, "moved_modules_of", None) != __name__]
sys.meta_path.append(_MovedModuleFinder(__name__))
