"""Helpers shared by the effect modules (not an effect: the leading underscore keeps it out of the report)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.config.settings import BRDFSettings, SimulationConfig  # noqa: E402
from core.geometry.scene import SceneGeometry  # noqa: E402
from tests.core.scenes import plate  # noqa: E402,F401  (the core tests' plate, one builder for both)

C = 299_792_458.0
FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def flash_config(range_m, pixels=8, subsamples=2, fov_rad=0.01, bins=256, bin_s=1e-9, margin_bins=64):
    """A flash config whose gate opens ``margin_bins`` before the echo of a surface at ``range_m``; one thread
    (deterministic and light on a shared machine)."""
    cfg = SimulationConfig()
    cfg.receiver.width_px = cfg.receiver.height_px = pixels
    cfg.receiver.subsamples = subsamples
    cfg.receiver.fov_x_rad = cfg.receiver.fov_y_rad = fov_rad
    cfg.gate.n_bins = bins
    cfg.gate.bin_width_s = bin_s
    cfg.gate.gate_start_s = max(0.0, 2 * range_m / C - margin_bins * bin_s)
    cfg.run.threads = 1
    return cfg


def mesh(vertices, triangles, brdf=None, name="object"):
    """A one-material SceneGeometry from vertex and triangle arrays."""
    tri = np.asarray(triangles)
    return SceneGeometry(np.asarray(vertices, float), tri.tolist(), [0] * len(tri), [brdf or BRDFSettings()], [name])


def uv_sphere(centre, radius, n_theta=96, n_phi=192):
    """Triangles of a UV sphere (vertices on the sphere)."""
    th = np.linspace(0, np.pi, n_theta + 1)
    ph = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    v = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3) * radius
    v += np.asarray(centre, float)
    idx = np.arange((n_theta + 1) * n_phi).reshape(n_theta + 1, n_phi)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    tris = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return v, tris


def cylinder(centre, radius, length, n_phi=256):
    """Triangles of an open cylinder with its axis along x (the sensor looks along −Z, so the side faces it)."""
    ph = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    ring = np.stack([np.zeros_like(ph), radius * np.cos(ph), radius * np.sin(ph)], -1)
    v = np.concatenate([ring + [-length / 2, 0, 0], ring + [length / 2, 0, 0]]) + np.asarray(centre, float)
    i = np.arange(n_phi)
    j = (i + 1) % n_phi
    tris = np.concatenate([np.stack([i, j, i + n_phi], -1), np.stack([j, j + n_phi, i + n_phi], -1)])
    return v, tris
