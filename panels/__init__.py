"""Properties-editor panels (camera Object Data, Scene and Material tabs), a 3D-viewport sidebar tab and the
status-bar progress of a running simulation."""
import bpy

from . import status
from .material import LADAR_PT_brdf
from .scene import (LADAR_PT_atmosphere, LADAR_PT_scene, LADAR_PT_scene_output, LADAR_PT_scene_results,
                    LADAR_PT_view3d, LADAR_PT_view3d_results)
from .sensor import (SENSOR_PANELS, LADAR_PT_sensor, LADAR_PT_sensor_detection, LADAR_PT_sensor_detector,  # noqa: F401
                     LADAR_PT_sensor_gate, LADAR_PT_sensor_gated, LADAR_PT_sensor_laser, LADAR_PT_sensor_receiver,
                     LADAR_PT_sensor_run, LADAR_PT_sensor_scanner)

CLASSES = (*SENSOR_PANELS, LADAR_PT_scene, LADAR_PT_scene_output, LADAR_PT_scene_results, LADAR_PT_atmosphere,
           LADAR_PT_brdf, LADAR_PT_view3d, LADAR_PT_view3d_results)

_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register():
    _register_classes()
    status.register()


def unregister():
    status.unregister()
    _unregister_classes()
