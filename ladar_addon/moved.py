"""Old import paths of names that moved to their own modules in the layered layout: they keep working for now,
with a ``DeprecationWarning`` naming the new path.  No imports of the add-on (any module may use it)."""
from __future__ import annotations

import importlib
import warnings


def moved_names(module: str, moved: dict):
    """A module ``__getattr__`` for ``module`` (its ``__name__``) that finds each name of ``moved`` (new sibling
    module → names it now holds) in its new module, warning once per access where it went."""
    package = module.rpartition(".")[0]
    short = module.rpartition(".")[2]

    def __getattr__(name):
        for new, names in moved.items():
            if name in names:
                warnings.warn(f"ladar_addon.{short}.{name} has moved to ladar_addon.{new}.{name}",
                              DeprecationWarning, stacklevel=2)
                return getattr(importlib.import_module(f"{package}.{new}"), name)
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return __getattr__
