"""Blender properties are generated 1:1 from the core settings, and Blender ↔ core round-trips exactly."""
import dataclasses
import math

import bpy
import pytest

from blender_scenes import add_camera, brdf_material

def _core_paths(config):
    paths = {"system_type"}
    for group in config.GROUPS:
        cls = type(getattr(config.SimulationConfig(), group))
        paths |= {f"{group}.{name}" for name, _, _ in config.field_specs(cls)}
    return paths


def test_every_core_setting_has_one_home_in_blender(lad):
    assert lad.fields.all_core_paths() == _core_paths(lad.config)
    brdf_attrs = set(lad.properties.LadarBRDFSettings.bl_rna.properties.keys()) - {"rna_type", "name"}
    # The measured table's lists (core.config.BRDF_TABLE_FIELDS) live in the "table" rows (ladar_addon.materials).
    assert brdf_attrs == {n for n, _, _ in lad.config.field_specs(lad.config.BRDFSettings)} | {
        "enabled", "table", "table_source", "origin", "plot"}


def test_property_definitions_follow_the_core_metadata(lad):
    props = lad.properties
    all_maps = [f for fields in props.SENSOR_FIELDS.values() for f in fields] + props.ATMOSPHERE_FIELDS + \
        props.BRDF_FIELDS
    assert len(all_maps) > 25
    for f in all_maps:
        rna = props.property_group_class(f.group).bl_rna.properties[f.attr]
        assert f.meta["doc"] in rna.description
        if f.kind == "enum":
            assert [i.identifier for i in rna.enum_items] == list(f.meta["choices"])
            assert rna.default == f.default
        elif f.kind == "bool":
            assert rna.default == f.default
        elif f.kind == "float":
            assert rna.subtype == f.subtype
            if f.meta["lo"] is not None and f.conversion == "":
                assert rna.hard_min == pytest.approx(f.meta["lo"], rel=1e-6)
            if f.meta["hi"] is not None and f.conversion == "":
                assert rna.hard_max == pytest.approx(f.meta["hi"], rel=1e-6)
            assert f.to_core(rna.default) == pytest.approx(f.default, rel=1e-6)
            if f.conversion == "pow10":  # stored and shown in the panel unit: 1e-12 A reads "1 pA"
                assert f"({f.meta['panel_unit']})" in rna.name
                assert f.to_blender(f.default) == pytest.approx(f.default / 10.0 ** f.exponent, rel=1e-12)
        elif f.kind == "int" and f.conversion == "":
            assert rna.default == f.default
            assert rna.hard_min == f.meta["lo"]
            assert rna.hard_max == min(f.meta["hi"], 2**31 - 1)
        if f.meta.get("unit") and f.subtype == "NONE" and f.kind in ("float", "int"):
            assert f"({f.unit_text()})" in rna.name  # unit in the label where Blender shows none
    # specific mappings
    laser = props.LadarLaserSettings.bl_rna.properties
    assert laser["wavelength_m"].subtype == "NONE" and laser["wavelength_m"].default == pytest.approx(1064.0)
    assert laser["wavelength_m"].name == "Wavelength (nm)"
    assert laser["pulse_fwhm_ns"].subtype == "NONE" and laser["pulse_fwhm_ns"].default == pytest.approx(5.0)
    assert laser["beam_divergence_mrad"].subtype == "NONE" and laser["beam_divergence_mrad"].default == pytest.approx(20.0)
    assert props.property_group_class("scanner").bl_rna.properties["scan_width_rad"].subtype == "ANGLE"  # degrees
    assert props.LadarReceiverSettings.bl_rna.properties["aperture_diameter_m"].subtype == "DISTANCE"
    assert props.LadarRunSettings.bl_rna.properties["max_memory_mib"].default == 4096
    assert "seed" not in props.LadarRunSettings.bl_rna.properties  # lives on Scene.ladar
    assert "fov_x_rad" not in props.LadarReceiverSettings.bl_rna.properties  # derived from the camera


def test_new_sensor_has_core_defaults_except_64x64(lad, scene):
    cam = add_camera(scene, width_px=64, height_px=64)
    cfg = lad.blend_config.config_from_blender(scene, cam)
    expected = lad.config.config_to_dict(lad.config.SimulationConfig())
    got = lad.config.config_to_dict(cfg)
    for d in (expected, got):
        d["receiver"].pop("fov_x_rad"), d["receiver"].pop("fov_y_rad")
    expected["receiver"]["width_px"] = expected["receiver"]["height_px"] = 64
    assert got == expected
    fresh = bpy.data.objects.new("fresh", bpy.data.cameras.new("fresh"))
    assert (fresh.ladar.receiver.width_px, fresh.ladar.receiver.height_px) == (64, 64)


def _non_default_config(lad):
    c = lad.config
    w, h = 40, 30
    fx = 0.0349
    cfg = c.SimulationConfig(
        laser=c.LaserSettings(pulse_energy_j=0.0025, wavelength_m=1.55e-06, pulse_shape="rectangular",
                              pulse_fwhm_s=7.5e-09, beam_profile="uniform", beam_divergence_rad=0.0042,
                              divergence_fills_fov=False),
        receiver=c.ReceiverSettings(width_px=w, height_px=h, fov_x_rad=fx,
                                    fov_y_rad=2 * math.atan(math.tan(fx / 2) * h / w), subsamples=3,
                                    aperture_diameter_m=0.12, system_efficiency=0.35),
        gate=c.RangeGateSettings(gate_start_s=8.5e-07, bin_width_s=5e-10, n_bins=2000),
        detection=c.DetectionSettings(max_echoes=5, threshold_j=2.5e-15, relative_threshold=0.1,
                                      interpolation="parabolic"),
        atmosphere=c.AtmosphereSettings(extinction_per_m=0.00012),
        run=c.RunSettings(seed=987654321, chunk_rays=65536, threads=2, save_waveforms=False,
                          max_memory_bytes=512 * 2**20),
        materials={"Paint": c.BRDFSettings(model="steinvall", reflectance=0.3, specular_a=0.05, slope_s=0.2,
                                           diffuse_b=0.08, diffuse_m=1.0),
                   "Grey10": c.BRDFSettings(reflectance=0.1)})
    # settings stored in powers of ten (tiny values such as Cn²) get a non-default value too
    for f in lad.fields.ATMOSPHERE_FIELDS + [f for fs in lad.fields.SENSOR_FIELDS.values() for f in fs]:
        if f.conversion == "pow10" and f.meta.get("subtype") != "WAVELENGTH":
            setattr(getattr(cfg, f.group), f.name, float(f"{(f.default or f.meta['hi'] / 400) * 2.5:.3g}"))
    # any other fields the core grows keep their defaults
    c.validate(cfg)
    return cfg


def _set_up(scene):
    cam = add_camera(scene)
    for name in ("Paint", "Grey10", "Unused"):
        bpy.data.materials.new(name)
    bpy.data.materials["Unused"].ladar_brdf.enabled = True  # not in the config: gets disabled
    return cam


def test_core_to_blender_to_core(lad, scene):
    cfg = _non_default_config(lad)
    cam = _set_up(scene)
    lad.blend_config.apply_config_to_blender(cfg, scene, cam)
    back = lad.blend_config.config_from_blender(scene, cam)
    want, got = lad.config.config_to_dict(cfg), lad.config.config_to_dict(back)
    for key in ("fov_x_rad", "fov_y_rad"):  # through the camera lens (float32): 1e-6 relative
        assert got["receiver"].pop(key) == pytest.approx(want["receiver"].pop(key), rel=1e-6)
    assert got == want  # every other value exactly, including 1.55 µm, 2.5e-15 J and the 32-bit-plus seed
    assert not bpy.data.materials["Unused"].ladar_brdf.enabled
    assert cam.ladar.laser.wavelength_m == pytest.approx(1550.0)  # stored in nm
    assert cam.ladar.run.max_memory_mib == 512


def test_blender_to_core_to_blender(lad, scene):
    cam = add_camera(scene, width_px=20, height_px=10, fov_rad=0.05)
    brdf_material("Board", model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08, diffuse_m=1.0)
    laser = cam.ladar.laser
    laser.pulse_energy_uj, laser.pulse_fwhm_ns, laser.pulse_shape = 4000.0, 3.0, "rectangular"
    cam.ladar.gate.gate_start_ns, cam.ladar.gate.n_bins = 1000.0, 777
    cam.ladar.detection.interpolation = "none"
    cam.ladar.receiver.aperture_diameter_m = 0.2
    scene.ladar.seed = 42
    scene.ladar_atmosphere.extinction_per_km = 0.3
    cfg1 = lad.blend_config.config_from_blender(scene, cam)

    bpy.ops.wm.read_homefile(use_empty=True)
    scene2 = bpy.context.scene
    cam2 = add_camera(scene2, width_px=64, height_px=64)
    bpy.data.materials.new("Board")
    lad.blend_config.apply_config_to_blender(cfg1, scene2, cam2)
    cfg2 = lad.blend_config.config_from_blender(scene2, cam2)
    d1, d2 = lad.config.config_to_dict(cfg1), lad.config.config_to_dict(cfg2)
    for key in ("fov_x_rad", "fov_y_rad"):
        assert d2["receiver"].pop(key) == pytest.approx(d1["receiver"].pop(key), rel=1e-6)
    assert d1 == d2
    assert d2["laser"]["pulse_energy_j"] == 0.004 and d2["gate"]["gate_start_s"] == 1e-6
    assert d2["materials"]["Board"]["specular_a"] == 0.05


def test_unit_scale_applies_to_distances(lad, scene):
    cam = add_camera(scene)
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = 0.01  # 1 Blender unit = 1 cm
    cam.ladar.receiver.aperture_diameter_m = 5.0  # 5 BU = 5 cm
    assert lad.blend_config.config_from_blender(scene, cam).receiver.aperture_diameter_m == pytest.approx(0.05)


def test_apply_refuses_bad_configs_and_changes_nothing(lad, scene):
    cam = _set_up(scene)
    before = lad.config.config_to_dict(lad.blend_config.config_from_blender(scene, cam))
    bad = _non_default_config(lad)
    bad.laser.pulse_energy_j = -1.0
    with pytest.raises(lad.config.ConfigError) as err:
        lad.blend_config.apply_config_to_blender(bad, scene, cam)
    assert err.value.field == "laser.pulse_energy_j"
    big_seed = _non_default_config(lad)
    big_seed.run.seed = 2**40
    with pytest.raises(lad.config.ConfigError) as err:
        lad.blend_config.apply_config_to_blender(big_seed, scene, cam)
    assert err.value.field == "run.seed"
    unknown = _non_default_config(lad)
    unknown.materials["Nope"] = lad.config.BRDFSettings()
    with pytest.raises(lad.config.ConfigError, match="Nope"):
        lad.blend_config.apply_config_to_blender(unknown, scene, cam)
    assert lad.config.config_to_dict(lad.blend_config.config_from_blender(scene, cam)) == before


def test_config_from_blender_needs_a_camera(lad, scene):
    empty = bpy.data.objects.new("Empty", None)
    with pytest.raises(lad.errors.LadarError, match="not a camera"):
        lad.blend_config.config_from_blender(scene, empty)
    with pytest.raises(lad.errors.LadarError, match="no ladar sensor"):
        lad.blend_config.config_from_blender(scene, None)


def test_brdf_of_materials(lad, scene):
    plain = bpy.data.materials.new("Plain")
    assert lad.blend_config.brdf_from_material(plain) == lad.config.DEFAULT_BRDF
    assert lad.blend_config.brdf_from_material(None) == lad.config.DEFAULT_BRDF
    paint = brdf_material("Paint", model="steinvall", specular_a=0.05, slope_s=0.2, diffuse_b=0.08)
    brdf = lad.blend_config.brdf_from_material(paint)
    assert dataclasses.astuple(brdf) == ("steinvall", 0.3, 0.05, 0.2, 0.08, 1.0, 1.064e-6, [], [])
