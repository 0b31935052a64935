"""Properties-editor panels (camera Object Data, Scene and Material tabs) and a 3D-viewport sidebar tab."""
import bpy

from .material import LADAR_PT_brdf
from .scene import LADAR_PT_atmosphere, LADAR_PT_scene, LADAR_PT_view3d
from .sensor import (EXTRA_GROUP_PANELS, LADAR_PT_sensor, LADAR_PT_sensor_detection, LADAR_PT_sensor_detector,
                     LADAR_PT_sensor_gate,
                     LADAR_PT_sensor_laser, LADAR_PT_sensor_receiver, LADAR_PT_sensor_run)

CLASSES = (LADAR_PT_sensor, LADAR_PT_sensor_laser, LADAR_PT_sensor_receiver, LADAR_PT_sensor_gate,
           LADAR_PT_sensor_detection, LADAR_PT_sensor_detector, LADAR_PT_sensor_run,
           *EXTRA_GROUP_PANELS, LADAR_PT_scene,
           LADAR_PT_atmosphere, LADAR_PT_brdf, LADAR_PT_view3d)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
