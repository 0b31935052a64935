"""Names the add-on's modules share (no imports: any module may use them)."""

#: Custom property that marks an object as a ladar result (value: its run folder); such objects are never exported
#: as scene geometry.
RESULT_TAG = "ladar_run"
