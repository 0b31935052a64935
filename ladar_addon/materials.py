"""Material-side ladar BRDF: the measured table stored in the .blend, table import, the Principled BSDF mapping
and the BRDF plot image.

Where a material's ladar BRDF lives (``Material.ladar_brdf``, see ``ladar_addon.properties``):

* the scalar settings of ``core.config.BRDFSettings`` (model, reflectance, Steinvall A/s/B/m, the table's
  wavelength) as generated properties;
* the measured table as a collection of rows ``table`` (:class:`LadarBRDFTableRow`: ``angle_deg``,
  ``brdf_per_sr``), saved in the .blend, so a file that uses a measured BRDF is self-contained; the file it
  came from is recorded in ``table_source`` (informative only: the file is not needed after the import);
* ``origin``: where the parameter values came from (a preset, the Principled BSDF mapping), shown in the panel;
* ``plot``: the last BRDF plot image (packed into the .blend).

Blender stores floats in single precision: table values come back as the shortest decimal that rounds to the
stored float32 (as every other setting, ``ladar_addon.properties``), and the table is validated again after
storing (two angles closer than float32 resolution are caught).
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import bpy

from ..core.config.settings import BRDFSettings
from ..core.config.validate import check_brdf_table
from ..core.errors import ConfigError
from .blend_config import brdf_from_material, config_from_blender, read_table, table_float, write_table
from .fields import BRDF_FIELDS


def _wavelength_field():
    return next(f for f in BRDF_FIELDS if f.name == "table_wavelength_m")


def import_brdf_table(material, path, wavelength_m: float | None = None) -> BRDFSettings:
    """Read a CSV/text BRDF table (``core.physics.brdf.load_brdf_table``), validate it and store it on ``material``:
    model "table", ladar BRDF enabled.  The wavelength is the one the file states, else ``wavelength_m``
    (ConfigError if neither).  Nothing changes on a bad file.  Returns the material's new BRDF settings."""
    from ..core.physics.brdf import load_brdf_table

    angles, values, file_wavelength_m = load_brdf_table(path)
    wavelength = file_wavelength_m if file_wavelength_m is not None else wavelength_m
    name = Path(path).name
    if wavelength is None:
        raise ConfigError(f"{name}: wavelength", None, "a wavelength stated in the file (e.g. "
                                                       "'# wavelength = 1064 nm') or given on import")
    field = _wavelength_field()
    lo, hi = field.meta["lo"], field.meta["hi"]
    if not lo <= wavelength <= hi:
        raise ConfigError(f"{name}: wavelength_m", wavelength, f"a wavelength in [{lo:g}, {hi:g}] m")
    # The float32 round trip must keep a valid table (angles closer than float32 resolution collapse).
    check_brdf_table([table_float(a) for a in angles], [table_float(v) for v in values],
                     f"{name}: ")
    props = material.ladar_brdf
    write_table(props, angles, values)
    setattr(props, field.attr, field.to_blender(wavelength))
    props.model = "table"
    props.table_source = name
    props.enabled = True
    return brdf_from_material(material)


# ------------------------------------------------------------------------------------------------------------
# Principled BSDF → starting Steinvall BRDF
# ------------------------------------------------------------------------------------------------------------
def _principled_node(material):
    tree = material.node_tree
    if bpy.app.version < (5, 0, 0) and not material.use_nodes:  # 5.0 always uses nodes (use_nodes deprecated)
        tree = None
    if tree is None:
        return None
    outputs = [n for n in tree.nodes if n.type == "OUTPUT_MATERIAL"]
    outputs.sort(key=lambda n: not n.is_active_output)
    for out in outputs:
        surface = out.inputs.get("Surface")
        if surface is not None and surface.is_linked and surface.links[0].from_node.type == "BSDF_PRINCIPLED":
            return surface.links[0].from_node
    return next((n for n in tree.nodes if n.type == "BSDF_PRINCIPLED"), None)


def principled_inputs(material) -> dict:
    """The Principled BSDF values the mapping uses: base colour (linear RGB), roughness, metallic, IOR and
    specular IOR level, with ``source`` (where they came from) and ``linked`` (inputs driven by a texture or
    node: their unlinked values are used).  Without a Principled BSDF node: the material's viewport display
    colour, roughness and metallic."""
    node = _principled_node(material)
    if node is None:
        return {"base_color": tuple(material.diffuse_color)[:3], "roughness": material.roughness,
                "metallic": material.metallic, "ior": 1.5, "specular_ior_level": 0.5,
                "source": "viewport display settings (no Principled BSDF node)", "linked": []}
    names = {"base_color": "Base Color", "roughness": "Roughness", "metallic": "Metallic", "ior": "IOR",
             "specular_ior_level": "Specular IOR Level"}
    defaults = {"ior": 1.5, "specular_ior_level": 0.5}
    values, linked = {}, []
    for key, socket_name in names.items():
        socket = node.inputs.get(socket_name)
        if socket is None:
            values[key] = defaults[key]
            continue
        value = socket.default_value
        values[key] = tuple(value)[:3] if key == "base_color" else float(value)
        if socket.is_linked:
            linked.append(socket_name)
    values.update(source=f"Principled BSDF node {node.name!r}", linked=linked)
    return values


def initialise_from_principled(material) -> tuple[BRDFSettings, dict]:
    """Set ``material``'s ladar BRDF to the starting Steinvall BRDF mapped from its Principled BSDF
    (``core.physics.brdf.brdf_from_principled``; the table, if any, is kept but unused).  Returns (BRDF, inputs)."""
    from ..core.physics.brdf import brdf_from_principled

    inputs = principled_inputs(material)
    brdf = brdf_from_principled(inputs["base_color"], inputs["roughness"], inputs["metallic"], inputs["ior"],
                                inputs["specular_ior_level"])
    props = material.ladar_brdf
    for f in BRDF_FIELDS:
        if f.name in ("model", "specular_a", "slope_s", "diffuse_b", "diffuse_m"):
            setattr(props, f.attr, f.to_blender(getattr(brdf, f.name)))
    props.origin = "Principled BSDF mapping: starting values, not a measurement"
    props.enabled = True
    return brdf_from_material(material), inputs


# ------------------------------------------------------------------------------------------------------------
# Plot
# ------------------------------------------------------------------------------------------------------------
def material_brdf_settings(material) -> BRDFSettings:
    """The BRDF as set on the material's panel (whether or not it is enabled)."""

    props = material.ladar_brdf
    return BRDFSettings(**{f.name: f.to_core(getattr(props, f.attr)) for f in BRDF_FIELDS}, **read_table(props))


def scene_laser_wavelength_m(scene) -> float | None:
    """The laser wavelength of the scene's ladar sensor (Scene > Ladar > Sensor, else the scene camera), or None
    when there is none or its settings cannot be read."""

    obj = (scene.ladar.sensor or scene.camera) if scene is not None else None
    if obj is None or obj.type != "CAMERA":
        return None
    try:
        return config_from_blender(scene, obj).laser.wavelength_m
    except Exception:  # noqa: BLE001 - an informative figure only (panels must draw)
        return None


def plot_image_name(material) -> str:
    return f"Ladar BRDF {material.name}"


def plot_material_brdf(material, laser_wavelength_m: float | None = None):
    """Plot the material's BRDF vs incidence angle (``core.fileio.preview.plot_brdf``: matplotlib, else a bare NumPy curve)
    into a packed Blender image (replacing the material's previous plot).  Returns the image.  A table that
    does not validate raises ConfigError and leaves the previous plot in place."""
    from ..core.fileio.preview import plot_brdf
    from ..core.config.validate import validate

    brdf = material_brdf_settings(material)
    validate(brdf, f"materials.{material.name}.")
    title = material.name + ("" if material.ladar_brdf.enabled else " (ladar BRDF off)")
    with tempfile.TemporaryDirectory(prefix="ladar_brdf_plot_") as tmp:
        path = plot_brdf(brdf, Path(tmp) / "brdf.png", title=title, laser_wavelength_m=laser_wavelength_m)
        image = bpy.data.images.load(str(path), check_existing=False)
        image.pack()
    old = material.ladar_brdf.plot
    image.name = plot_image_name(material)
    image.filepath_raw = f"//{bpy.path.clean_name(image.name)}.png"
    material.ladar_brdf.plot = image
    if old is not None and old != image and old.users == 0:
        bpy.data.images.remove(old)
    image.name = plot_image_name(material)  # the old one is gone: take its name
    return image


def table_summary_lines(props, laser_wavelength_m: float | None = None, max_rows: int = 10) -> list[str]:
    """Lines describing a material's stored table (rows, wavelength, source) for the panel."""
    table = read_table(props)
    angles, values = table["table_angle_deg"], table["table_brdf_per_sr"]
    if not angles:
        return ["No table: import a CSV/text file (angle in degrees, BRDF in 1/sr)"]
    wavelength_nm = _wavelength_field().to_core(getattr(props, _wavelength_field().attr)) * 1e9
    head = f"{len(angles)} rows at {wavelength_nm:.0f} nm"
    if props.table_source:
        head += f", from {props.table_source}"
    lines = [head]
    try:
        check_brdf_table(angles, values)
    except ConfigError as exc:
        lines.append(f"Invalid table: {exc}")
    if laser_wavelength_m and abs(laser_wavelength_m * 1e9 - wavelength_nm) > 0.02 * wavelength_nm:
        lines.append(f"Measured at {wavelength_nm:.0f} nm, the laser is at {laser_wavelength_m * 1e9:.0f} nm")
    shown = list(zip(angles, values))
    if len(shown) > max_rows:
        shown = shown[: max_rows - 1] + [shown[-1]]
    for i, (a, v) in enumerate(shown):
        if len(angles) > max_rows and i == max_rows - 1:
            lines.append(f"… {len(angles) - max_rows} more rows …")
        lines.append(f"θ = {a:g}°   f_r = {v:.4g} 1/sr")
    lines.append("Linear in θ between rows; last value held up to 90°")
    return lines

