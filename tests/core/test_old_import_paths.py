"""Modules moved into the layered layout keep their old import path for now, with a DeprecationWarning naming
the new one, and resolve to the very same module object (no copy, no shim file)."""
import importlib
import sys
import warnings

import pytest

import core

OLD_NAMES = sorted(core.MOVED_MODULES)


@pytest.mark.parametrize("old", OLD_NAMES)
def test_old_path_is_the_new_module_and_says_where_to_go(old):
    new = importlib.import_module(f"core.{core.MOVED_MODULES[old]}")
    sys.modules.pop(f"core.{old}", None)
    with pytest.warns(DeprecationWarning, match=rf"core\.{old} has moved to core\.{core.MOVED_MODULES[old]}"):
        mod = importlib.import_module(f"core.{old}")
    assert mod is new
    assert mod.__name__ == mod.__spec__.name == f"core.{core.MOVED_MODULES[old]}"


def test_from_imports_through_old_paths_keep_working():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from core.pipeline import run_simulation, simulate_frame  # noqa: F401
        from core.receiver import ChainSettings, apply_receiver_chain  # noqa: F401
        from core.runio import write_run  # noqa: F401
        from core.scanner import n_scan_pulses  # noqa: F401
    from core.config import ConfigError, SimulationConfig  # the documented entry point: no warning
    from core.errors import ConfigError as moved
    assert ConfigError is moved and SimulationConfig.__module__ == "core.config.settings"


def test_unknown_names_are_not_invented():
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("core.no_such_module")
