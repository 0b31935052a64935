"""The noisy receiver chain run through the Blender operator (bpy.ops.ladar.simulate): detector.mode = noisy on
the sensor, the run metadata says the chain ran (with its steps, noise sampling route and false-alarm record),
and the imported point cloud carries a finite positive per-point SNR."""
import json

import bpy
import numpy as np

from blender_scenes import add_camera, add_plate

FOV = 0.004  # rad: a 16×16 receiver sees 0.4 m × 0.4 m at 100 m


def _attribute(obj, name, dtype=np.float32):
    attr = obj.data.attributes[name]
    out = np.empty(len(attr.data), dtype)
    attr.data.foreach_get("value", out)
    return out


def test_operator_runs_the_noisy_receiver(lad, scene, tmp_path):
    cam = add_camera(scene, width_px=16, height_px=16, fov_rad=FOV)
    cam.ladar.receiver.subsamples = 2
    det = cam.ladar.detector
    det.mode = "noisy"
    det.detector_type = "apd"
    det.background_rate_photons_per_s = 5e8  # 0.2 primaries per 1 ns bin at η 0.4
    cam.ladar.run.save_counts = True  # counts kept: the per-bin reference route (run.save_counts)
    add_plate(scene, size=2.0, location=(0, 0, -100.0))
    scene.ladar.output_dir = str(tmp_path / "runs")
    assert bpy.ops.ladar.simulate() == {"FINISHED"}
    run = tmp_path / "runs" / "Ladar_f0001"
    meta = json.loads((run / "metadata.json").read_text())
    assert meta["settings"]["detector"]["mode"] == "noisy"
    assert "receiver_chain" in meta["stages_run"] and "receiver_chain" not in meta["stages_skipped"]
    rx = meta["receiver"]
    assert {"photon_conversion", "shot_noise", "background", "gain", "excess_noise", "read_noise", "adc"} \
        <= set(rx["steps_run"])
    assert rx["units"] == "counts" and rx["noise_sampling"] == "table" and rx["noise_sigma"] > 0
    fa = rx["false_alarms"]
    assert fa["n_pixels"] == 256 and fa["n_false_alarms"] >= 0 and fa["expected_false_alarms_gaussian"] >= 0
    counts = np.load(run / "counts.npy")
    assert counts.shape[:2] == (16, 16) and counts.dtype == np.uint16
    obj = bpy.data.objects["Ladar_f0001"]
    snr = _attribute(obj, "snr")
    assert len(snr) >= 256 and np.all(np.isfinite(snr)) and np.all(snr > 0)
    # every pixel sees the plate far above the noise; any other echo is a noise false alarm, counted as such
    # (the guard around a true return is ±2 pulse widths = ±1.5 m here)
    range_m = _attribute(obj, "range_m")
    px, py = _attribute(obj, "pixel_x", np.int32), _attribute(obj, "pixel_y", np.int32)
    on_plate = np.abs(range_m - 100.0) < 0.05
    assert len(set(zip(px[on_plate], py[on_plate]))) == 256 and np.median(snr[on_plate]) > 10
    far = np.abs(range_m - 100.0) > 1.6
    assert np.count_nonzero(far) <= fa["n_false_alarms"] <= np.count_nonzero(~on_plate)
