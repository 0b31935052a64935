"""``bpy.ops.ladar.simulate`` (a frame or a frame range) and ``bpy.ops.ladar.simulate_cancel``.

Invoked from the interface the simulation runs as a modal operator: the core works in a worker thread, a timer
calls :meth:`SimulationJob.step` on the main thread, the status bar shows a progress bar (``panels.status``) and
ESC (or the status bar's cancel button) stops it within one block of rays, leaving nothing behind.  Executed
from a script or in background mode it runs to the end before returning (progress lines are printed).
"""
import bpy

from ..core.errors import ConfigError
from ..core.errors import Cancelled
from ..ladar_addon.errors import LadarError
from ..ladar_addon.background import current_job, handle_modal_event, set_current_job
from ..ladar_addon.run_inputs import progress_printer

_USER_ERRORS = (ConfigError, LadarError, Cancelled, OSError)


def tag_redraw(context):
    wm = context.window_manager
    for window in getattr(wm, "windows", ()):
        for area in window.screen.areas:
            if area.type in ("STATUSBAR", "PROPERTIES", "VIEW_3D"):
                area.tag_redraw()


class JobModal:
    """The modal part the simulation and sweep operators share: watch a threaded job from a timer, pass ESC to
    it, report its end, stop it when Blender aborts the operator.  Subclasses set ``FINISHED_PREFIX`` and
    ``CANCEL_WAIT_S`` and say what a cancelled job keeps (``cancelled_text``)."""

    FINISHED_PREFIX = "Ladar: "
    CANCEL_WAIT_S = 10.0

    def cancelled_text(self, job) -> str:
        raise NotImplementedError

    def _watch(self, context, job, interval_s):
        set_current_job(job)
        self._job_ref = job
        wm = context.window_manager
        self._timer = wm.event_timer_add(interval_s, window=context.window)
        wm.modal_handler_add(self)
        tag_redraw(context)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job_ref
        outcome = handle_modal_event(job, event.type, event.value)
        if outcome in ("PASS_THROUGH", "RUNNING_MODAL"):
            if event.type == "TIMER":
                tag_redraw(context)
            return {outcome}
        self._end(context)
        if outcome == "FINISHED":
            self.report({"INFO"}, f"{self.FINISHED_PREFIX}{job.summary()}")
            for w in job.warnings():
                self.report({"WARNING"}, f"Ladar: {w}")
            return {"FINISHED"}
        if job.state == "failed":
            self.report({"ERROR"}, job.summary())
        else:
            self.report({"WARNING"}, self.cancelled_text(job))
        return {"CANCELLED"}

    def cancel(self, context):
        """Blender aborts the operator (a file is loaded, the window closes): stop the worker and clean up."""
        job = getattr(self, "_job_ref", None)
        if job is not None and not job.finished:
            job.cancel()
            job.wait(timeout_s=self.CANCEL_WAIT_S)
        self._end(context)

    def _end(self, context):
        timer = getattr(self, "_timer", None)
        if timer is not None:
            context.window_manager.event_timer_remove(timer)
            self._timer = None
        set_current_job(None)
        tag_redraw(context)


class LADAR_OT_simulate(JobModal, bpy.types.Operator):
    """Simulate the ladar sensor (the current frame, or a frame range): write a run folder and import its point \
cloud and images.  ESC cancels"""

    bl_idname = "ladar.simulate"
    bl_label = "Simulate Ladar"
    bl_options = {"REGISTER"}

    sensor: bpy.props.StringProperty(
        name="Sensor", default="",
        description="Camera object to simulate (empty: Scene > Ladar > Sensor, else the scene camera)")
    frames: bpy.props.StringProperty(
        name="Frames", default="",
        description='Frames to simulate into one sequence run folder, e.g. "1-100", "1-100:5" or "1,5,9" '
                    "(empty: the current frame, or the scene's frame range when Scene > Ladar > Frame Range is on)")

    @classmethod
    def poll(cls, context):
        if current_job() is not None:
            cls.poll_message_set("A ladar simulation is running (ESC cancels it)")
            return False
        return context.scene is not None

    def _job(self, context, progress=None):
        # imported here, not when the add-on is enabled: the simulator (numba, SciPy, its kernels' modules) was
        # nearly all of enabling it (0.5-0.75 s of CPU: docs/performance.md, issue 25), and what runs no
        # simulation (export-config, a refused config, the panels) never needs it
        from ..ladar_addon.frames import parse_frames
        from ..ladar_addon.job import SimulationJob

        scene = context.scene
        sensor = None
        if self.sensor:
            sensor = bpy.data.objects.get(self.sensor)
            if sensor is None:
                raise LadarError(f"no object named {self.sensor!r}")
        frames = None
        if self.frames.strip():
            frames = parse_frames(self.frames)
        elif scene.ladar.use_frame_range:
            frames = list(range(scene.frame_start, scene.frame_end + 1, max(1, scene.frame_step)))
        return SimulationJob(scene, frames=frames, sensor=sensor, progress=progress)

    def execute(self, context):
        """Blocking run (scripts, background mode)."""
        printer = progress_printer() if bpy.app.background else None
        try:
            job = self._job(context, printer)
            job.run()
        except _USER_ERRORS as exc:
            self.report({"ERROR"}, str(exc) or type(exc).__name__)
            return {"CANCELLED"}
        finally:
            if printer is not None:
                printer.close()
        self.report({"INFO"}, f"Ladar: {job.summary()}")
        for w in job.warnings():
            self.report({"WARNING"}, f"Ladar: {w}")
        return {"FINISHED"}

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        try:
            job = self._job(context)
            job.start(threaded=True)  # claims the run folder's name: another run may hold it
        except _USER_ERRORS as exc:
            self.report({"ERROR"}, str(exc) or type(exc).__name__)
            return {"CANCELLED"}
        return self._watch(context, job, 0.1)

    def cancelled_text(self, job) -> str:
        return f"Ladar: {job.run_name} cancelled, nothing written"


class LADAR_OT_warm_up(JobModal, bpy.types.Operator):
    """Compile the simulator's kernels now (once per install and CPU; later runs load them from the cache) so that
    no simulation waits for the compiler.  Runs in the background with progress in the status bar; ESC cancels"""

    bl_idname = "ladar.warm_up"
    bl_label = "Compile Ladar Kernels"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        if current_job() is not None:
            cls.poll_message_set("A ladar job is running (ESC cancels it)")
            return False
        return True

    def execute(self, context):
        """Blocking run (scripts, background mode): the progress lines are printed."""
        from ..ladar_addon.warmup import WarmUpJob

        job = WarmUpJob()
        job.start(threaded=False)
        if job.state != "done":
            self.report({"ERROR"}, job.summary())
            return {"CANCELLED"}
        self.report({"INFO"}, f"Ladar: {job.summary()}")
        return {"FINISHED"}

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        from ..ladar_addon.warmup import WarmUpJob

        job = WarmUpJob()
        job.start(threaded=True)
        return self._watch(context, job, 0.2)

    def cancelled_text(self, job) -> str:
        return "Ladar: kernel warm-up stopped; what it compiled is kept, the rest compiles on first use"


class LADAR_OT_simulate_cancel(bpy.types.Operator):
    """Cancel the running ladar simulation (nothing of it is written or imported)"""

    bl_idname = "ladar.simulate_cancel"
    bl_label = "Cancel Ladar Simulation"

    @classmethod
    def poll(cls, context):
        return current_job() is not None

    def execute(self, context):
        job = current_job()
        if job is not None:
            job.cancel()
        return {"FINISHED"}
