"""The running simulation in the status bar: a progress bar with the run's state and a cancel button."""
import bpy


def draw_status(self, context):
    """Appended to ``STATUSBAR_HT_header``: draws nothing unless a ladar simulation runs."""
    from ..ladar_addon.background import current_job

    job = current_job()
    if job is None:
        return
    row = self.layout.row(align=True)
    row.progress(factor=job.fraction, type="BAR", text=job.status_text())
    row.operator("ladar.simulate_cancel", text="", icon="CANCEL")


def register():
    bpy.types.STATUSBAR_HT_header.append(draw_status)


def unregister():
    bpy.types.STATUSBAR_HT_header.remove(draw_status)
