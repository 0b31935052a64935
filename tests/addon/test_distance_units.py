"""Distance settings are stored in Blender units (m / scale_length): their ranges hold every SI value the core
accepts at any unit scale, so nothing is clipped on the way into a .blend (presets, loaded configs)."""
import pytest

from blender_scenes import add_camera


def _distance_fields(lad):
    props = lad.properties
    fields = [f for fs in props.SENSOR_FIELDS.values() for f in fs] + props.ATMOSPHERE_FIELDS
    return [f for f in fields if f.conversion == "distance"]


def test_distance_ranges_cover_every_unit_scale(lad):
    fields = _distance_fields(lad)
    assert {f.path for f in fields} >= {"laser.beam_focus_range_m", "laser.beam_waist_radius_m",
                                        "receiver.aperture_diameter_m", "atmosphere.visibility_m"}
    s_min, s_max = lad.properties.SCALE_LENGTH_RANGE
    assert s_min == pytest.approx(1e-9, rel=1e-6) and s_max == pytest.approx(1e9, rel=1e-6)
    for f in fields:
        rna = lad.properties.property_group_class(f.group).bl_rna.properties[f.attr]
        lo, hi = f.meta["lo"], f.meta["hi"]
        # hard range: the SI limits expressed at the smallest/largest metres-per-unit Blender allows
        assert rna.hard_max == pytest.approx(hi / s_min, rel=1e-6), f.path
        assert rna.hard_min == pytest.approx(lo / s_max, rel=1e-6, abs=1e-30), f.path
        # slider range: the SI range at 1 m per unit
        assert rna.soft_max == pytest.approx(hi, rel=1e-6) and rna.soft_min == pytest.approx(lo, rel=1e-6)


@pytest.mark.parametrize("scale_length, path, value_m", [
    (0.001, "laser.beam_focus_range_m", 1.0e7),     # 1 mm units: the core's largest focus range is 1e10 BU
    (0.001, "receiver.aperture_diameter_m", 10.0),  # 1e4 BU
    (1000.0, "laser.beam_waist_radius_m", 1.0e-4),  # 1 km units: the smallest waist is 1e-7 BU
])
def test_extreme_values_survive_odd_unit_scales(lad, scene, path, value_m, scale_length):
    cam = add_camera(scene)
    cfg = lad.blend_config.config_from_blender(scene, cam)  # valid settings, read at 1 m per unit
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = scale_length
    group, name = path.split(".")
    setattr(getattr(cfg, group), name, value_m)
    lad.blend_config.apply_config_to_blender(cfg, scene, cam)
    stored = getattr(getattr(cam.ladar, group), name)
    assert stored == pytest.approx(value_m / scale_length, rel=1e-6)  # in Blender units, not clipped
    back = lad.blend_config.config_from_blender(scene, cam)
    assert getattr(getattr(back, group), name) == pytest.approx(value_m, rel=1e-6)


def test_out_of_range_distance_is_reported_in_metres(lad, scene):
    cam = add_camera(scene)
    cfg = lad.blend_config.config_from_blender(scene, cam)
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = 0.001
    lad.blend_config.apply_config_to_blender(cfg, scene, cam)  # every distance re-expressed in millimetres
    cam.ladar.receiver.aperture_diameter_m = 20_000.0  # 20 m: above the core's 10 m, not clipped in Blender
    cfg = lad.blend_config.config_from_blender(scene, cam)
    assert cfg.receiver.aperture_diameter_m == pytest.approx(20.0)
    with pytest.raises(lad.config.ConfigError, match=r"receiver\.aperture_diameter_m = 20\.0.*10\] m"):
        lad.config.validate(cfg)


@pytest.mark.parametrize("scale_length", [1.0, 0.001])
def test_inner_and_outer_scale_are_scene_distances(lad, scene, scale_length):
    """Issue 17: l0 and L0 are atmosphere distance properties (Blender units): 5 mm and 50 m survive the round
    trip at 1 m and 1 mm per unit, and the panel field list carries them with the statistics model."""
    cam = add_camera(scene)
    cfg = lad.blend_config.config_from_blender(scene, cam)
    assert cfg.atmosphere.scintillation_statistics == "wave_optics"
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = scale_length
    cfg.atmosphere.inner_scale_m = 0.005
    cfg.atmosphere.outer_scale_m = 50.0
    lad.blend_config.apply_config_to_blender(cfg, scene, cam)
    assert scene.ladar_atmosphere.inner_scale_m == pytest.approx(0.005 / scale_length, rel=1e-6)
    back = lad.blend_config.config_from_blender(scene, cam)
    assert back.atmosphere.inner_scale_m == pytest.approx(0.005, rel=1e-6)
    assert back.atmosphere.outer_scale_m == pytest.approx(50.0, rel=1e-6)
    names = {f.name: f for f in lad.properties.ATMOSPHERE_FIELDS}
    assert names["inner_scale_m"].conversion == "distance" and names["outer_scale_m"].conversion == "distance"
    assert names["scintillation_statistics"].kind == "enum"
