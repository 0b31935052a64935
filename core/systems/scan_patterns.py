"""Scan patterns of the time-of-flight scanner (paper §2.1) and the sub-rays of its beam.

Scan patterns (angles in the sensor frame: −Z forward, +Y up, +X right; α to +X, β to +Y,
d = (cos β sin α, sin β, −cos β cos α)), pulse k fired at t_k = k / PRF:

* raster       unidirectional lines, line period 1/scan_rate, α sweeps −W/2 → +W/2, lines from β = +H/2 down;
* oscillating  a sinusoidal across-track mirror α = (W/2) sin(2π f t), β = 0 (along-track from motion);
* rotating     a head spinning about +Y, α = −W/2 + 2π f t, n_channels fired together at β ∈ [+H/2, −H/2];
* palmer       a conical scan: the beam at the cone half angle c around −Z, azimuth φ = 2π f t; with a second
               half angle c_y (``cone_half_angle_y_rad``) an elliptic cone, d ∝ (tan c cos φ, tan c_y sin φ, −1):
               on any plane normal to −Z the beam draws the ellipse of semi-axes tan c and tan c_y (times the
               distance) at the eccentric angle φ, off-nadir c in the X–Z plane and c_y in the Y–Z plane;
* risley       rotating wedge prisms on the −Z axis (a rosette): each emitter's beam refracted exactly at both
               faces of every prism, prism i turned to ψ_i = −(2π f_i t + φ_i) (core/config/tables.py).

The rotating head with a channel table (``scanner.channel_table`` or ``channel_table_file``): channel c fires at
t_k + τ_c, at elevation β_c and azimuth α = −W/2 + 2π f (t_k + τ_c) + Δα_c; without one the channels are spaced
evenly over H and fire together.

The beam footprint is sampled by rings of sub-rays of equal energy: ring k > 0 holds 6k rays and the rings'
boundaries enclose the cumulative energy fractions (1 + 3k(k+1))/N of the beam; each ray sits at the angle that
halves its ring's energy, so the N sub-rays carry exactly the pulse energy (Gaussian: enclosed fraction
1 − exp(−2ρ²/θ²) with θ the 1/e² half-angle; uniform: ρ²/θ²).  Each ring is turned by its own azimuth
offset (:func:`ring_offsets_rad`): no line through the beam centre carries rays of two rings, none of the axes
carries a ray.
"""
from __future__ import annotations

import functools

import numpy as np

from ..config.derived import n_pulse_times
from ..config.settings import SimulationConfig
from ..config.tables import channel_table_deg, risley_emitters_deg, risley_prisms, risley_trace, scan_channels
from ..errors import ConfigError
from ..geometry.motion import Trajectory
from ..jit import kernel


# ----------------------------------------------------------------------------------------------------------
# Scan pattern
# ----------------------------------------------------------------------------------------------------------
def direction_from_angles(alpha, beta):
    """Unit vectors (n, 3) in the sensor frame for horizontal angle α (to +X) and vertical angle β (to +Y)."""
    cb = np.cos(beta)
    return np.stack([cb * np.sin(alpha), np.sin(beta) * np.ones_like(alpha), -cb * np.cos(alpha)], axis=-1)


def pulse_schedule(config: SimulationConfig, start: int = 0, stop: int | None = None, indices=None):
    """Pulses [start, stop) (or the given pulse ``indices``) of the scan: (time_s (n,) float64, direction (n, 3)
    sensor frame, channel (n,) int16, scan_angle_rad (n,) float64 — the across-scan angle α, or the azimuth for
    the rotating head and palmer).

    Pulses are numbered in time order; the rotating head's channels fired at one time are consecutive.
    """
    s = config.scanner
    n_ch = scan_channels(s)
    total = n_pulse_times(config) * n_ch
    stop = total if stop is None else min(stop, total)
    idx = np.arange(start, stop, dtype=np.int64) if indices is None else np.asarray(indices, dtype=np.int64)
    k, channel = idx // n_ch, idx % n_ch
    t = k / s.pulse_rate_hz
    if s.pattern == "raster":
        line_period = 1.0 / s.scan_rate_hz
        line = np.floor(t / line_period + 1e-9)
        u = t / line_period - line
        alpha = -0.5 * s.scan_width_rad + s.scan_width_rad * u
        step = s.scan_height_rad / max(s.n_lines - 1, 1)
        beta = 0.5 * s.scan_height_rad - step * np.minimum(line, s.n_lines - 1) if s.n_lines > 1 else 0.0 * t
        d = direction_from_angles(alpha, beta)
        angle = alpha
    elif s.pattern == "oscillating":
        alpha = 0.5 * s.scan_width_rad * np.sin(2 * np.pi * s.scan_rate_hz * t)
        d = direction_from_angles(alpha, np.zeros_like(alpha))
        angle = alpha
    elif s.pattern == "rotating":
        table = channel_table_deg(s)
        if table is None:
            alpha = -0.5 * s.scan_width_rad + 2 * np.pi * s.scan_rate_hz * t
            elevations = (np.linspace(0.5 * s.scan_height_rad, -0.5 * s.scan_height_rad, n_ch) if n_ch > 1
                          else np.zeros(1))
            d = direction_from_angles(alpha, elevations[channel])
        else:  # the channel fires fire_offset_s after k/PRF, at its elevation and azimuth offset
            table = table[:n_ch]
            t = t + table[channel, 2]
            alpha = (-0.5 * s.scan_width_rad + 2 * np.pi * s.scan_rate_hz * t
                     + np.radians(table[channel, 1]))
            d = direction_from_angles(alpha, np.radians(table[channel, 0]))
        angle = np.mod(alpha + np.pi, 2 * np.pi) - np.pi
    elif s.pattern == "risley":
        d = risley_directions(s, t, channel)
        angle = np.arctan2(d[:, 1], d[:, 0])
    else:  # palmer
        phi = 2 * np.pi * s.scan_rate_hz * t
        c = s.cone_half_angle_rad
        if s.cone_half_angle_y_rad:  # elliptic cone: (tan c cos φ, tan c_y sin φ, −1), normalised
            d = np.stack([np.tan(c) * np.cos(phi), np.tan(s.cone_half_angle_y_rad) * np.sin(phi),
                          -np.ones_like(phi)], axis=-1)
            d /= np.linalg.norm(d, axis=1, keepdims=True)
        else:
            d = np.stack([np.sin(c) * np.cos(phi), np.sin(c) * np.sin(phi), -np.cos(c) * np.ones_like(phi)],
                         axis=-1)
        angle = np.mod(phi + np.pi, 2 * np.pi) - np.pi
    return t, d, channel.astype(np.int16), angle


def risley_directions(scanner, t_s, emitter):
    """Directions (n, 3) leaving the Risley prisms at times ``t_s`` for beams from emitters ``emitter`` (n,):
    the emitter's beam (α, β of ``risley_emitters_deg``) refracted exactly (Snell's law in vector form) at both
    faces of every prism in turn (core/config/tables.py: :func:`~core.config.tables.risley_trace`)."""
    prisms = risley_prisms(scanner)
    a, b = np.radians(risley_emitters_deg(scanner)).T
    incident = direction_from_angles(a[emitter], b[emitter])
    d, tir = risley_trace(np.asarray(t_s, dtype=np.float64), incident, prisms)
    if tir.any():
        raise ConfigError("scanner.risley_wedge_deg", [float(w) for w in prisms[:, 1]],
                          "wedge angles and indices without total internal reflection")
    return d


# ----------------------------------------------------------------------------------------------------------
# Beam sub-rays
# ----------------------------------------------------------------------------------------------------------
def beam_subrays(n_rings: int, profile: str = "gaussian"):
    """Equal-energy sub-rays of a beam: (ρ/θ (m,), azimuth φ (m,), energy fraction (m,)) with
    m = 1 + 3R(R+1) and θ the 1/e² half-angle (Gaussian) or the edge half-angle (uniform)."""
    counts = np.array([1] + [6 * k for k in range(1, n_rings + 1)])
    m = int(counts.sum())
    cum = np.cumsum(counts) / m             # energy enclosed by each ring's outer boundary
    inner = np.concatenate([[0.0], cum[:-1]])
    mid = 0.5 * (inner + cum)               # each ray at the angle that halves its ring's energy
    mid[0] = 0.0                            # the centre ray sits on the axis
    if profile == "gaussian":
        rho = np.sqrt(-0.5 * np.log1p(-mid))
    else:
        rho = np.sqrt(mid)
    offsets = ring_offsets_rad(n_rings)
    rho_all, phi_all = [], []
    for k, n in enumerate(counts):
        j = np.arange(n)
        rho_all.append(np.full(n, rho[k]))
        phi_all.append(offsets[k] + 2 * np.pi * j / n)
    return np.concatenate(rho_all), np.concatenate(phi_all), np.full(m, 1.0 / m)


#: Directions (rad, modulo π) no ring ray should sit on: the beam frame's axes and diagonals, along which scene
#: edges (walls, kerbs, building corners) most often cross a beam.
_RING_AVOID_RAD = (0.0, 0.25 * np.pi, 0.5 * np.pi, 0.75 * np.pi)


@functools.lru_cache(maxsize=None)
def _ring_offset_table(n_rings: int) -> tuple:
    offsets, lines = [0.0], np.array(_RING_AVOID_RAD)
    for k in range(1, n_rings + 1):
        period = np.pi / (3 * k)  # ring k's 6k rays lie on 3k lines through the centre, π/(3k) apart
        cand = (np.arange(256) + 0.5) / 256 * period
        mine = (cand[:, None] + period * np.arange(3 * k)[None, :]) % np.pi
        gap = np.abs((mine[:, :, None] - lines[None, None, :] + 0.5 * np.pi) % np.pi - 0.5 * np.pi).min(axis=(1, 2))
        best = float(cand[np.argmax(gap)])
        offsets.append(best)
        lines = np.concatenate([lines, (best + period * np.arange(3 * k)) % np.pi])
    return tuple(offsets)


def subray_offsets(laser, rho_unit, phi, width_scale: float = 1.0):
    """Angular offsets (ρ (m,) rad from the beam axis, azimuth φ (m,) in the beam frame u ≈ +X, v ≈ +Y) of the
    sub-rays of :func:`beam_subrays` for the laser's beam.

    Circular beam (``beam_divergence_y_rad`` 0): ρ = ρ/θ · θ with θ = beam_divergence_rad/2 (the 1/e² half
    angle, Gaussian; the edge, uniform).  Elliptical beam: the circular pattern's unit offsets (x, y) are scaled
    to a = beam_divergence_rad/2 along the axis at ``beam_orientation_rad`` from u and b =
    beam_divergence_y_rad/2 across it.  The linear map carries the circular profile's equal-energy cells onto the
    elliptical profile's (I ∝ exp(−2x'²/a² − 2y'²/b²), or uniform over the ellipse), so every sub-ray keeps its
    equal share of the energy exactly and the sub-rays' second moments are those of the circular pattern times
    a² and b² along the axes."""
    a = 0.5 * laser.beam_divergence_rad * width_scale
    if not laser.beam_divergence_y_rad:
        return rho_unit * a, phi
    b = 0.5 * laser.beam_divergence_y_rad * width_scale
    psi = laser.beam_orientation_rad
    x, y = rho_unit * np.cos(phi - psi) * a, rho_unit * np.sin(phi - psi) * b  # in the ellipse's axes
    return np.hypot(x, y), np.arctan2(y, x) + psi


def ring_offsets_rad(n_rings: int) -> np.ndarray:
    """Azimuth of the first ray of each ring (ring 0: the centre ray, 0).

    A ring of 6k evenly spaced rays puts pairs of opposite rays on 3k lines through the beam centre; with every
    ring starting at the same azimuth those lines coincide, and an edge along one of them (the old layout: the
    beam's x and y axes) finds two rays of every ring on it (217 rays: 117 on one closed side, 0.540 of the
    energy instead of ≈ 0.5).  Each ring is turned by its own offset, chosen ring by ring (deterministically) to
    keep its lines as far as possible from the earlier rings' lines and from the axes and diagonals: no line
    through the centre carries rays of two rings, so a half-plane through the centre holds half of the ring
    rays, and no ray sits on the axes.  A ring's offset does not depend on the number of rings."""
    return np.asarray(_ring_offset_table(max(16, n_rings))[: n_rings + 1])


def _perpendicular_axes(d):
    """Unit vectors u (≈ +X) and v (≈ +Y) perpendicular to unit directions d (n, 3)."""
    up = np.zeros_like(d)
    up[:, 1] = 1.0
    u = np.cross(d, up)
    norm = np.linalg.norm(u, axis=1)
    along_y = norm < 1e-9
    u[along_y] = (1.0, 0.0, 0.0)
    norm[along_y] = 1.0
    u /= norm[:, None]
    v = np.cross(u, d)
    return u, v


@kernel
def _subray_directions(centre, rot, cos_rho, sin_rho, cos_phi, sin_phi, out):
    """World directions (n·m, 3) of the m sub-rays of n beams: sub-ray j of beam i is
    cos ρ_j c + sin ρ_j (cos φ_j u + sin φ_j v) for the beam centre c (sensor frame) and the unit axes
    u = c × ŷ/|c × ŷ| (x̂ when c ∥ ŷ), v = u × c of :func:`_perpendicular_axes`, turned into the world by
    ``rot`` (one (3, 3) rotation, or one per beam).  One beam (m = 1): the centre itself."""
    n, m = centre.shape[0], cos_rho.shape[0]
    per_beam = rot.shape[0] > 1
    for i in range(n):
        cx, cy, cz = centre[i, 0], centre[i, 1], centre[i, 2]
        ux, uy, uz = -cz, 0.0, cx  # c × ŷ
        norm = np.sqrt(ux * ux + uz * uz)
        if norm < 1e-9:
            ux, uy, uz, norm = 1.0, 0.0, 0.0, 1.0
        ux, uz = ux / norm, uz / norm
        vx, vy, vz = uy * cz - uz * cy, uz * cx - ux * cz, ux * cy - uy * cx  # u × c
        r = rot[i] if per_beam else rot[0]
        for j in range(m):
            if m == 1:
                dx, dy, dz = cx, cy, cz
            else:
                ox = cos_phi[j] * ux + sin_phi[j] * vx
                oy = cos_phi[j] * uy + sin_phi[j] * vy
                oz = cos_phi[j] * uz + sin_phi[j] * vz
                dx = cos_rho[j] * cx + sin_rho[j] * ox
                dy = cos_rho[j] * cy + sin_rho[j] * oy
                dz = cos_rho[j] * cz + sin_rho[j] * oz
            k = i * m + j
            for a in range(3):
                out[k, a] = r[a, 0] * dx + r[a, 1] * dy + r[a, 2] * dz


def scan_beams(config: SimulationConfig, trajectory: Trajectory, start: int, stop: int, *, wander_rad=None,
               width_scale: float = 1.0):
    """The beams of pulses [start, stop): (time_s, channel, scan_angle, origin (n, 3), nominal axis (n, 3)
    in world coordinates, sub-ray directions (n·m, 3)), the m sub-rays of a pulse consecutive (all from the
    pulse's origin).

    ``wander_rad`` (n, 2) displaces each beam's centre (beam wander, turbulence), ``width_scale`` widens the
    beam (turbulent broadening); the nominal axis is what the sensor believes it fired along."""
    laser = config.laser
    t_s, d_sensor, channel, angle = pulse_schedule(config, start, stop)
    n = len(t_s)
    origin, rot = trajectory.poses_at(t_s)
    if trajectory.rotation_is_constant:
        rot = trajectory.rotation0
        axis_world = d_sensor @ rot.T
    else:
        axis_world = np.einsum("nij,nj->ni", rot, d_sensor)
    rho_unit, phi, weight = beam_subrays(config.scanner.beam_subray_rings, laser.beam_profile)
    m = len(weight)
    centre = d_sensor
    if wander_rad is not None and np.any(wander_rad):
        u, v = _perpendicular_axes(d_sensor)
        centre = d_sensor + wander_rad[:, :1] * u + wander_rad[:, 1:] * v
        centre /= np.linalg.norm(centre, axis=1, keepdims=True)
    rho, phi = subray_offsets(laser, rho_unit, phi, width_scale)
    d_world = np.empty((n * m, 3))
    _subray_directions(np.ascontiguousarray(centre), np.ascontiguousarray(rot.reshape(-1, 3, 3)), np.cos(rho),
                       np.sin(rho), np.cos(phi), np.sin(phi), d_world)
    return t_s, channel, angle, origin, axis_world, d_world


def scan_rays(config: SimulationConfig, trajectory: Trajectory, start: int, stop: int, *, wander_rad=None,
              width_scale: float = 1.0):
    """:func:`scan_beams` with one origin per sub-ray: (time_s, channel, scan_angle, origin (n, 3), nominal axis
    (n, 3), ray origins (n·m, 3), ray directions (n·m, 3))."""
    t_s, channel, angle, origin, axis_world, d_world = scan_beams(config, trajectory, start, stop,
                                                                  wander_rad=wander_rad, width_scale=width_scale)
    m = len(d_world) // max(len(t_s), 1)
    return t_s, channel, angle, origin, axis_world, np.repeat(origin, m, axis=0), d_world
