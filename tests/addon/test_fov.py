"""Receiver field of view from the camera: the formula, Blender's own camera frame, and the inverse."""
import math

import pytest

from blender_scenes import add_camera


def test_formula_numbers(lad):
    fov = lad.sensor.receiver_fov_rad
    a = math.radians(2.0)
    # square receiver: both sides get the camera angle, whatever the fit
    for fit in ("AUTO", "HORIZONTAL", "VERTICAL"):
        assert fov(fit, a, 64, 64) == pytest.approx((a, a), rel=1e-15)
    # horizontal fit, 64×32: fov_y = 2 atan(tan(fov_x/2)·H/W)
    fx, fy = fov("HORIZONTAL", a, 64, 32)
    assert fx == pytest.approx(a, rel=1e-15)
    assert fy == pytest.approx(2 * math.atan(math.tan(a / 2) * 32 / 64), rel=1e-15)
    assert fy == pytest.approx(0.0174546217654, rel=1e-10)  # 1.0000762°: not exactly half of 2°
    # vertical fit, 64×32: the angle is the vertical one
    fx, fy = fov("VERTICAL", a, 64, 32)
    assert fy == pytest.approx(a, rel=1e-15)
    assert fx == pytest.approx(2 * math.atan(math.tan(a / 2) * 2), rel=1e-15)
    # auto fit follows the larger side
    assert fov("AUTO", a, 64, 32) == fov("HORIZONTAL", a, 64, 32)
    assert fov("AUTO", a, 32, 64) == fov("VERTICAL", a, 32, 64)


@pytest.mark.parametrize("fit", ["AUTO", "HORIZONTAL", "VERTICAL"])
@pytest.mark.parametrize("size", [(64, 64), (80, 40), (30, 90)])
def test_matches_blenders_camera_frame(lad, scene, fit, size):
    """The receiver sees exactly what Blender would render at width_px × height_px (Camera.view_frame)."""
    w, h = size
    obj = add_camera(scene, width_px=w, height_px=h, fov_rad=math.radians(3.0), sensor_fit=fit)
    obj.data.sensor_height = 20.0  # differs from the width, so a wrong sensor choice would show
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    frame = obj.data.view_frame(scene=scene)
    half_x = max(abs(v.x / v.z) for v in frame)
    half_y = max(abs(v.y / v.z) for v in frame)
    fx, fy = lad.sensor.camera_receiver_fov_rad(obj.data, w, h)
    assert math.tan(fx / 2) == pytest.approx(half_x, rel=1e-5)
    assert math.tan(fy / 2) == pytest.approx(half_y, rel=1e-5)
    # config_from_blender uses the same derivation
    cfg = lad.blend_config.config_from_blender(scene, obj)
    assert (cfg.receiver.fov_x_rad, cfg.receiver.fov_y_rad) == (fx, fy)


@pytest.mark.parametrize("fit", ["AUTO", "HORIZONTAL", "VERTICAL"])
def test_set_camera_fov_is_the_inverse(lad, scene, fit):
    obj = add_camera(scene, sensor_fit=fit)
    w, h = 48, 36
    fx = 0.03
    fy = 2 * math.atan(math.tan(fx / 2) * h / w)
    lad.sensor.set_camera_receiver_fov(obj.data, fx, fy, w, h)
    assert lad.sensor.camera_receiver_fov_rad(obj.data, w, h) == pytest.approx((fx, fy), rel=1e-6)


def test_inconsistent_or_unsupported_cameras_are_refused(lad, scene):
    obj = add_camera(scene)
    with pytest.raises(lad.config.ConfigError) as err:
        lad.sensor.set_camera_receiver_fov(obj.data, 0.03, 0.03, 64, 32)  # not square pixels
    assert err.value.field == "receiver.fov_y_rad"
    obj.data.type = "ORTHO"
    with pytest.raises(lad.config.ConfigError) as err:
        lad.sensor.camera_receiver_fov_rad(obj.data, 64, 64)
    assert "PERSP" in str(err.value)
    obj.data.type = "PERSP"
    obj.data.shift_x = 0.1
    with pytest.raises(lad.config.ConfigError, match="shift"):
        lad.sensor.camera_receiver_fov_rad(obj.data, 64, 64)
