"""``bpy.ops.ladar.sweep``: run a sweep file on Dask from the interface (a file browser picks the sweep file).

Invoked from the interface it is a modal operator over :class:`ladar_addon.sweep.SweepJob`, the same pattern as
``ladar.simulate``: the scene is exported on the main thread, the sweep runs in a worker thread, a timer polls the
job, the status bar shows the tasks done, the total and the ETA, and ESC (or the status bar's cancel button) stops
it — finished points are kept and running the same sweep into the same folder resumes it.  Executed from a script
or in background mode it runs to the end before returning.
"""
import bpy
from bpy_extras.io_utils import ImportHelper

from ..core.errors import ConfigError
from ..core.errors import Cancelled
from ..ladar_addon.errors import LadarError
from ..ladar_addon.background import current_job
from ..ladar_addon.run_inputs import progress_printer
from .simulate import JobModal

_USER_ERRORS = (ConfigError, LadarError, Cancelled, OSError, RuntimeError)


class LADAR_OT_sweep(JobModal, bpy.types.Operator, ImportHelper):
    """Run a parameter sweep (a TOML sweep file) of the ladar sensor on Dask into a sweep folder: a results table \
and plots.  ESC cancels (finished points are kept; the same sweep resumes)"""

    bl_idname = "ladar.sweep"
    bl_label = "Run Ladar Sweep"
    bl_options = {"REGISTER"}

    filter_glob: bpy.props.StringProperty(default="*.toml;*.json", options={"HIDDEN"})
    out_dir: bpy.props.StringProperty(name="Sweep Folder", subtype="DIR_PATH", default="//sweeps/sweep",
                                      description="Folder of the sweep (runs, results.csv, plots); the same sweep "
                                                  "run into it again resumes it")
    scheduler: bpy.props.StringProperty(name="Scheduler", default="",
                                        description="A running Dask scheduler, e.g. tcp://host:8786 (empty: a local "
                                                    "cluster, one worker process per core)")
    workers: bpy.props.IntProperty(name="Workers", default=0, min=0, max=1024,
                                   description="Worker processes of the local cluster (0: one per core)")
    restart: bpy.props.BoolProperty(name="Restart", default=False,
                                    description="Discard the sweep folder's runs, table and plots and start again "
                                                "(needed when the sweep file, settings or scene changed)")

    @classmethod
    def poll(cls, context):
        if current_job() is not None:
            cls.poll_message_set("A ladar simulation or sweep is running (ESC cancels it)")
            return False
        return context.scene is not None

    def _job(self, context, progress=None):
        from ..ladar_addon.sweep import SweepJob  # (here: the simulator and Dask are not needed to enable the add-on)

        return SweepJob(context.scene, self.filepath, self.out_dir, scheduler=self.scheduler or None,
                        n_workers=self.workers or None, restart=self.restart, progress=progress)

    def execute(self, context):
        if not bpy.app.background and context.window is not None:
            return self._start_modal(context)
        printer = progress_printer("ladar: sweep ")
        try:
            job = self._job(context, printer)
            job.run()
        except _USER_ERRORS as exc:
            self.report({"ERROR"}, str(exc) or type(exc).__name__)
            return {"CANCELLED"}
        finally:
            printer.close()
        self.report({"INFO"}, f"Ladar {job.summary()}")
        return {"FINISHED"}

    def _start_modal(self, context):
        try:
            job = self._job(context)
        except _USER_ERRORS as exc:
            self.report({"ERROR"}, str(exc) or type(exc).__name__)
            return {"CANCELLED"}
        job.start(threaded=True)
        return self._watch(context, job, 0.2)

    FINISHED_PREFIX = "Ladar "
    CANCEL_WAIT_S = 30.0

    def cancelled_text(self, job) -> str:
        return f"Ladar sweep {job.run_name} cancelled: finished points kept (run it again to resume)"


CLASSES = (LADAR_OT_sweep,)
