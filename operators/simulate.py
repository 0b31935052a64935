"""``bpy.ops.ladar.simulate``: simulate the active ladar sensor at the current frame."""
import bpy

from ..core.config import ConfigError
from ..core.pipeline import Cancelled
from ..ladar_addon.errors import LadarError
from ..ladar_addon.simulate import simulate_scene


class LADAR_OT_simulate(bpy.types.Operator):
    """Simulate the ladar sensor at the current frame: write a run folder and import its point cloud and images"""

    bl_idname = "ladar.simulate"
    bl_label = "Simulate Ladar"
    bl_options = {"REGISTER"}

    sensor: bpy.props.StringProperty(
        name="Sensor", default="",
        description="Camera object to simulate (empty: Scene > Ladar > Sensor, else the scene camera)")

    @classmethod
    def poll(cls, context):
        return context.scene is not None

    def execute(self, context):
        scene = context.scene
        sensor = None
        if self.sensor:
            sensor = bpy.data.objects.get(self.sensor)
            if sensor is None:
                self.report({"ERROR"}, f"no object named {self.sensor!r}")
                return {"CANCELLED"}
        wm = context.window_manager
        progress = None
        if not bpy.app.background and wm is not None:
            wm.progress_begin(0, 100)

            def progress(fraction, message=""):
                wm.progress_update(int(100 * fraction))
        try:
            run_path, result = simulate_scene(scene, sensor=sensor, progress=progress)
        except (ConfigError, LadarError, Cancelled, OSError) as exc:
            self.report({"ERROR"}, str(exc) or type(exc).__name__)
            return {"CANCELLED"}
        finally:
            if progress is not None:
                wm.progress_end()
        self.report({"INFO"}, f"Ladar: {len(result.points['range_m'])} points in {run_path}")
        return {"FINISHED"}
