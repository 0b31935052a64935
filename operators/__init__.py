"""Operators: thin wrappers around ``ladar_addon`` functions."""
import bpy

from .config_io import LADAR_OT_export_config, LADAR_OT_load_config
from .results import CLASSES as RESULT_CLASSES
from .simulate import LADAR_OT_simulate, LADAR_OT_simulate_cancel, LADAR_OT_warm_up

CLASSES = (LADAR_OT_simulate, LADAR_OT_simulate_cancel, LADAR_OT_warm_up, LADAR_OT_export_config, LADAR_OT_load_config,
           *RESULT_CLASSES)
from . import materials  # noqa: E402 - material BRDF operators (table import, Principled mapping, plot)
CLASSES += materials.CLASSES
from . import export_las  # noqa: E402 - LAS 1.4 export of a run's point cloud
CLASSES += export_las.CLASSES
from . import sweep  # noqa: E402 - parameter sweeps on Dask
CLASSES += sweep.CLASSES
from . import channel_table  # noqa: E402 - the rotating head's channel table from a CSV file
CLASSES += channel_table.CLASSES
from . import aerosol_layers  # noqa: E402 - clear the atmosphere's aerosol layers (set by a config file)
CLASSES += aerosol_layers.CLASSES


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register_classes()
    export_las.register_menu()


def unregister():
    export_las.unregister_menu()
    _unregister_classes()
