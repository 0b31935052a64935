"""Drawing helpers shared by the panels."""


def draw_fields(layout, props, fields, skip=()):
    """One row per generated property (labels, units and ranges come from the property definitions)."""
    for f in fields:
        if f.attr not in skip:
            layout.prop(props, f.attr)


def simulate_button(layout, sensor_name=""):
    row = layout.row()
    row.scale_y = 1.4
    op = row.operator("ladar.simulate", text="Simulate", icon="RENDER_STILL")
    op.sensor = sensor_name
