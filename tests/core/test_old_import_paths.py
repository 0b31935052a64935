"""Modules moved or split in the layered layout keep their old import path for now, with a DeprecationWarning
naming the new one.  A module moved whole resolves to the very same module object (no copy, no shim file); the
old path of a split module finds each name in the module that now holds it."""
import importlib
import sys
import warnings

import pytest

import core

MOVED_WHOLE = sorted(k for k, v in core.MOVED_MODULES.items() if isinstance(v, str))
SPLIT = sorted(k for k, v in core.MOVED_MODULES.items() if not isinstance(v, str))


@pytest.mark.parametrize("old", MOVED_WHOLE)
def test_old_path_is_the_new_module_and_says_where_to_go(old):
    new = importlib.import_module(f"core.{core.MOVED_MODULES[old]}")
    sys.modules.pop(f"core.{old}", None)
    with pytest.warns(DeprecationWarning, match=rf"core\.{old} has moved to core\.{core.MOVED_MODULES[old]}"):
        mod = importlib.import_module(f"core.{old}")
    assert mod is new
    assert mod.__name__ == mod.__spec__.name == f"core.{core.MOVED_MODULES[old]}"


@pytest.mark.parametrize("old", SPLIT)
def test_old_path_of_a_split_module_names_its_parts(old):
    sys.modules.pop(f"core.{old}", None)
    with pytest.warns(DeprecationWarning, match=rf"core\.{old} was split into core\.{core.MOVED_MODULES[old][0]}"):
        mod = importlib.import_module(f"core.{old}")
    for home in core.MOVED_MODULES[old]:
        part = importlib.import_module(f"core.{home}")
        public = [n for n in vars(part) if not n.startswith("_") and getattr(part, n).__class__.__name__ == "function"
                  and getattr(part, n).__module__ == part.__name__]
        for name in public:
            assert getattr(mod, name) is getattr(part, name)
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        mod.no_such_name  # noqa: B018


def test_from_imports_through_old_paths_keep_working():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from core.pipeline import Cancelled, FrameResult, run_simulation, simulate, simulate_frame  # noqa: F401
        from core.propagation import prepare_frame_atmosphere, stage_seed  # noqa: F401
        from core.receiver import ChainSettings, apply_receiver_chain  # noqa: F401
        from core.runio import write_run  # noqa: F401
        from core.scanner import n_scan_pulses, pulse_schedule, simulate_scan  # noqa: F401
        from core.brdf import evaluate_brdf, plot_brdf  # noqa: F401
    from core.run import run_simulation as new
    assert run_simulation is new
    from core.config import ConfigError, SimulationConfig  # the documented entry point: no warning
    from core.errors import ConfigError as moved
    assert ConfigError is moved and SimulationConfig.__module__ == "core.config.settings"


def test_unknown_names_are_not_invented():
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("core.no_such_module")
