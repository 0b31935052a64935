"""Weather in the waveform: returns from the atmosphere itself (docs/theory.md §14, docs/atmosphere.md).

Two parts, both added to a pixel's (or pulse's) waveform before the receiver chain:

* **Volume backscatter** (single scattering, homogeneous medium).  A beam carrying the fraction F of the pulse
  energy E_T into a pixel's field of view returns from the slab [R, R + dR]

      dE = E_T η_sys π r_a² · F · β · O(R) · exp(−2αR) / R² · dR                                  (W1)

  (the lidar equation P(R) = E (c/2) β A_r O(R) R⁻² e^(−2αR) written per range instead of per time; the pixel's
  solid angle cancels: the illuminated volume Ω R² dR times the irradiance F E/(Ω R²)).  Each waveform bin
  collects W1 convolved with the pulse and integrated over the bin.  Quadrature: the range is cut into slabs of
  a quarter of min(bin width, pulse FWHM) (in round-trip time); each slab's energy is W1 integrated by 8-point
  Gauss–Legendre (relative error < 1e-10 for O = 1; with the geometric overlap, at its kinks, < 1e-4 of a slab)
  and placed at the slab's energy centroid, then binned exactly with the pulse like any surface return
  (core/physics/waveform.py).  Placing a slab at its centroid errs by the slab's second moment, (δt)²/12 with
  δt ≤ min(Δ, FWHM)/4: < 0.3 % of the waveform in L2 (measured against direct quadrature: tests/core/atmosphere/
  test_weather.py).  The closed form of the O = 1 integral, for checks:
  ∫_a^b e^(−2αR)/R² dR = e^(−2αa)/a − e^(−2αb)/b − 2α [E₁(2αa) − E₁(2αb)].
* **Discrete scatterers** (rain, snow): particles at least ``drop_min_diameter_mm`` across are drawn one by one
  from the size distribution N(D) = N₀ exp(−ΛD) (Marshall & Palmer 1948 for rain: N₀ = 8000 m⁻³ mm⁻¹,
  Λ = 4.1 R^−0.21 mm⁻¹; Gunn & Marshall 1958 for snow, melted diameter: N₀ = 3800 R^−0.87, Λ = 2.55 R^−0.48)
  uniformly in each beam's cone between ``backscatter_min_range_m`` and the gate end.  A drop of geometric
  area A = πD²/4 at range R in a beam of solid angle Ω intercepts the fraction f = min(1, A/(ΩR²)) of the beam's
  energy and sends back 2/S of it per steradian (extinction efficiency 2, lidar ratio S: the same β = α/S as
  the volume, so the expected sum of the drops is W1 with β of the drops):

      E_d = E_T η_sys π r_a² · F · f · (2/S) · O(R) · exp(−2αR) / (R² + r_a²)                      (W2)

  and it shadows the fraction f of the beam for every later return of that beam (surfaces and drops; the
  return path's shadow and the volume behind a drop are not reduced).  The smaller particles (D < D_min) add
  β = (2/S)(π/4) ∫₀^Dmin N(D) D² dD to the volume part.

Extinction α of rain: 1.076 R^0.67 dB/km (Carbonneau & Wisely 1998, the near-IR free-space-optics relation;
Kaushal & Kaddoum 2017, IEEE Comm. Surveys & Tutorials 19(1), Table); dry snow: (5.42e-5 λ_nm + 5.4958776)
R^1.38 dB/km (same review).  Haze/fog: Kim/Kruse from the visibility (extinction.py) and β = α/S, S ≈ 18–20 sr
for water fog in the near IR (e.g. Pinnick et al. 1983, J. Atmos. Sci. 40; Klett 1985).

Overlap O(R) (``overlap_model = geometric``): the transmitted beam is a disc of radius r_t + R θ_t, the receiver's
field of view (a flash pixel's, or the scanner receiver's = the beam's divergence) a disc of radius r_a + R θ_r,
their axes parallel and ``tx_rx_offset_m`` = d apart (in the direction ``tx_rx_offset_angle_deg`` from the
sensor frame's +x); O is the area of their intersection over the area of the
smaller disc (the fraction of the smaller cone that the other one covers; 0 while the discs are apart, → 1 at
long range).  Per pixel (flash): the on-axis O(R) times the parallax tilt of the Gaussian beam across the field,
exp(4 z (t·u) d/(w² + b²)), u the offset's direction (:func:`pixel_overlap`, docs/theory.md §14 W3), for flash
and gated pixels.

This module does not import bpy.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import exp1

from .extinction import two_way_transmission

DB_PER_KM_TO_PER_M = math.log(10.0) / 10.0 / 1000.0
WEATHER_CONDITIONS = ("none", "haze", "fog", "rain", "snow", "custom")
#: 8-point Gauss-Legendre nodes and weights on [-1, 1] for the slab integrals (here and in physics.weather_waveform)
GL_X, GL_W = np.polynomial.legendre.leggauss(8)


# ------------------------------------------------------------------------------------------------------------
# Coefficients from named conditions
# ------------------------------------------------------------------------------------------------------------
def rain_extinction_per_m(rate_mm_h):
    """Rain extinction α (1/m) in the near IR: 1.076 R^0.67 dB/km (module docstring).  10 mm/h → 5.033 dB/km."""
    return 1.076 * np.asarray(rate_mm_h, dtype=np.float64) ** 0.67 * DB_PER_KM_TO_PER_M


def snow_extinction_per_m(rate_mm_h, wavelength_m):
    """Dry-snow extinction α (1/m): (5.42e-5 λ_nm + 5.4958776) R^1.38 dB/km (module docstring)."""
    a = 5.42e-5 * (wavelength_m * 1e9) + 5.4958776
    return a * np.asarray(rate_mm_h, dtype=np.float64) ** 1.38 * DB_PER_KM_TO_PER_M


def size_distribution(condition: str, rate_mm_h: float):
    """(N₀ in m⁻³ mm⁻¹, Λ in mm⁻¹) of N(D) = N₀ e^(−ΛD): Marshall–Palmer rain or Gunn–Marshall snow."""
    r = float(rate_mm_h)
    if condition == "rain":
        return 8000.0, 4.1 * r ** -0.21
    if condition == "snow":
        return 3800.0 * r ** -0.87, 2.55 * r ** -0.48
    raise ValueError(f"condition must be 'rain' or 'snow', got {condition!r}")


def number_above(n0, lam, d_min_mm):
    """Particles per m³ with D ≥ d_min: (N₀/Λ) e^(−Λ D_min)."""
    return n0 / lam * math.exp(-lam * d_min_mm)


def small_drop_backscatter(n0, lam, d_min_mm, lidar_ratio_sr):
    """β (1/(m sr)) of the particles with D < D_min: (2/S)(π/4) N₀ ∫₀^Dmin D² e^(−ΛD) dD (mm² → m²)."""
    x = lam * d_min_mm
    moment2 = 2.0 / lam ** 3 * (1.0 - math.exp(-x) * (1.0 + x + 0.5 * x * x))  # mm³ · (mm⁻¹ of N₀) → mm²
    return (2.0 / lidar_ratio_sr) * (math.pi / 4.0) * n0 * moment2 * 1e-6


@dataclass(frozen=True)
class Weather:
    """The weather of a run: what the waveform stage adds (module docstring)."""

    condition: str
    extinction_per_m: float        # the weather's own extinction, added to the aerosol's (rain, snow)
    backscatter_per_m_sr: float    # volume β
    lidar_ratio_sr: float
    n0: float = 0.0                # discrete particles: N₀ (m⁻³ mm⁻¹), Λ (mm⁻¹), D_min (mm), density ≥ D_min (m⁻³)
    lam: float = 0.0
    d_min_mm: float = 0.0
    drop_density_per_m3: float = 0.0

    @property
    def has_drops(self) -> bool:
        return self.drop_density_per_m3 > 0.0

    def record(self) -> dict:
        out = {"condition": self.condition, "extinction_per_m": self.extinction_per_m,
               "backscatter_per_m_sr": self.backscatter_per_m_sr, "lidar_ratio_sr": self.lidar_ratio_sr}
        if self.has_drops:
            out.update(n0_per_m3_mm=self.n0, lambda_per_mm=self.lam, drop_min_diameter_mm=self.d_min_mm,
                       drop_density_per_m3=self.drop_density_per_m3)
        return out


def weather_model(atm, wavelength_m: float, aerosol_extinction_per_m: float) -> Weather | None:
    """The :class:`Weather` of ``atm`` (AtmosphereSettings), None for weather = none.  ``aerosol_extinction_per_m``:
    α of the visibility / extinction setting (extinction.py), whose β = α/S is the haze/fog volume part."""
    cond = atm.weather
    if cond == "none":
        return None
    s = atm.lidar_ratio_sr
    if cond == "custom":
        return Weather(cond, 0.0, atm.backscatter_per_m_sr, s)
    beta_aerosol = aerosol_extinction_per_m / s
    if cond in ("haze", "fog"):
        return Weather(cond, 0.0, beta_aerosol, s)
    n0, lam = size_distribution(cond, atm.rain_rate_mm_h)
    alpha = float(rain_extinction_per_m(atm.rain_rate_mm_h) if cond == "rain"
                  else snow_extinction_per_m(atm.rain_rate_mm_h, wavelength_m))
    beta = beta_aerosol + small_drop_backscatter(n0, lam, atm.drop_min_diameter_mm, s)
    return Weather(cond, alpha, beta, s, n0, lam, atm.drop_min_diameter_mm,
                   number_above(n0, lam, atm.drop_min_diameter_mm))


# ------------------------------------------------------------------------------------------------------------
# Overlap
# ------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Overlap:
    """Geometric transmitter/receiver overlap (module docstring); ``model = none``: O = 1."""

    model: str = "none"
    offset_m: float = 0.0
    tx_radius_m: float = 0.0
    tx_half_angle: float = 0.0
    rx_radius_m: float = 0.0
    rx_half_angle: float = 0.0
    offset_angle_rad: float = 0.0  # direction of the transmitter from the receiver in the tan plane (0: +x)

    def __call__(self, range_m):
        r = np.asarray(range_m, dtype=np.float64)
        if self.model == "none":
            return np.ones_like(r)
        a = self.tx_radius_m + r * self.tx_half_angle
        b = self.rx_radius_m + r * self.rx_half_angle
        return disc_overlap_fraction(a, b, self.offset_m)

    def record(self) -> dict:
        return dict(vars(self))


def disc_overlap_fraction(a, b, d):
    """|disc(a) ∩ disc(b)| / (π min(a, b)²) for discs of radii a, b whose centres are d apart."""
    a, b, d = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64), np.asarray(d, np.float64))
    small = np.minimum(a, b)
    out = np.where(d <= np.abs(a - b), 1.0, 0.0)
    part = (d > np.abs(a - b)) & (d < a + b)
    if np.any(part):  # d > |a − b| ≥ 0 there
        ap, bp, d = a[part], b[part], d[part]
        c1 = np.clip((d * d + ap * ap - bp * bp) / (2 * d * ap), -1.0, 1.0)
        c2 = np.clip((d * d + bp * bp - ap * ap) / (2 * d * bp), -1.0, 1.0)
        k = (-d + ap + bp) * (d + ap - bp) * (d - ap + bp) * (d + ap + bp)
        area = ap * ap * np.arccos(c1) + bp * bp * np.arccos(c2) - 0.5 * np.sqrt(np.maximum(k, 0.0))
        out[part] = area / (np.pi * small[part] ** 2)
    return np.clip(out, 0.0, 1.0)


def pixel_overlap(overlap: Overlap, range_m, tan_x, tan_y, beam_profile: str = "gaussian"):
    """O(R) of a flash pixel whose axis is (tan_x, tan_y) in the tan plane (module docstring, "per pixel"):
    the on-axis overlap O(R) times the parallax tilt of the Gaussian beam across the field,
    T = exp(4 z (t·u) d / (w² + b²)) with z = R/√(1 + t²) the depth, w = r_t + z θ_t the beam's 1/e² radius,
    b = r_a + z θ_r the radius of the pixel's view, d the offset and u = (cos φ, sin φ) its direction in the tan
    plane (φ = ``offset_angle_rad``; 0: the transmitter at +d along x, t·u = t_x exactly).  T = 1 on axis
    (t = 0: :class:`Overlap` exactly), with d = 0, for ``model = none`` (O = 1) and for a uniform beam.
    Broadcasts."""
    r = np.asarray(range_m, dtype=np.float64)
    return overlap(r) * overlap_tilt(overlap, r, tan_x, tan_y, beam_profile)


def overlap_tilt(overlap: Overlap, range_m, tan_x, tan_y, beam_profile: str = "gaussian"):
    """T of :func:`pixel_overlap` (ones where it is 1 by construction).  Broadcasts."""
    r = np.asarray(range_m, dtype=np.float64)
    tx, ty = np.asarray(tan_x, np.float64), np.asarray(tan_y, np.float64)
    if overlap.model == "none" or beam_profile == "uniform" or overlap.offset_m == 0.0:
        return np.ones(np.broadcast_shapes(r.shape, tx.shape, ty.shape))
    z = r / np.sqrt(1.0 + tx * tx + ty * ty)
    w = overlap.tx_radius_m + z * overlap.tx_half_angle
    b = overlap.rx_radius_m + z * overlap.rx_half_angle
    phi = overlap.offset_angle_rad
    along = tx if phi == 0.0 else tx * math.cos(phi) + ty * math.sin(phi)  # t·u
    return np.exp(4.0 * z * along * overlap.offset_m / (w * w + b * b))


# ------------------------------------------------------------------------------------------------------------
# Volume backscatter
# ------------------------------------------------------------------------------------------------------------
def closed_form_integral(a_m, b_m, alpha_per_m):
    """∫_a^b e^(−2αR)/R² dR in closed form (module docstring); α = 0: 1/a − 1/b."""
    a, b, al = float(a_m), float(b_m), float(alpha_per_m)
    if al == 0.0:
        return 1.0 / a - 1.0 / b
    return (math.exp(-2 * al * a) / a - math.exp(-2 * al * b) / b
            - 2 * al * (float(exp1(2 * al * a)) - float(exp1(2 * al * b))))


def layers_closed_form_integral(table):
    """Σ_i β_i ∫_{s_i}^{e_i} e^(−2τ(R))/R² dR of aerosol layers in clear air (α₀ = β₀ = 0), ``table`` rows
    [s_i, e_i, α_i, β_i] in increasing range: inside layer i, τ(R) = τ(s_i) + α_i (R − s_i), so each term is
    β_i e^(−2(τ(s_i) − α_i s_i)) × :func:`closed_form_integral` (s_i, e_i, α_i) (docs/theory.md §14 W4)."""
    total, tau = 0.0, 0.0
    for s, e, a, b in np.asarray(table, np.float64):
        total += b * math.exp(-2.0 * (tau - a * s)) * closed_form_integral(s, e, a)
        tau += a * (e - s)
    return total


def layer_backscatter(table):
    """β(R) (1/(m sr)) of the aerosol layers, ``table`` (n, 4) rows [start_m, end_m, α, β] (core.config.tables.
    aerosol_layer_table): Σ_i β_i 1[s_i ≤ R < e_i], a callable; None without a layer of β > 0."""
    rows = [(float(a), float(b), float(beta)) for a, b, _, beta in np.asarray(table, np.float64) if beta > 0.0]
    if not rows:
        return None

    def beta_of(range_m):
        r = np.asarray(range_m, np.float64)
        out = np.zeros(r.shape)
        for a, b, beta in rows:
            out += np.where((r >= a) & (r < b), beta, 0.0)
        return out
    return beta_of


def slab_integrals(edges_m, alpha_per_m, overlap: Overlap, weight=None):
    """Per slab [edges[i], edges[i+1]]: ∫ w(R) O(R) e^(−2αR)/R² dR and the energy centroid range (8-point
    Gauss–Legendre); ``weight`` = w(R) (a callable; None: 1).  ``alpha_per_m``: α, or a layered extinction
    (core.atmosphere.extinction.LayeredExtinction: e^(−2τ(R)))."""
    lo, hi = edges_m[:-1], edges_m[1:]
    half = 0.5 * (hi - lo)
    mid = 0.5 * (hi + lo)
    r = mid[:, None] + half[:, None] * GL_X[None, :]
    g = overlap(r) * two_way_transmission(alpha_per_m, r) / (r * r)
    if weight is not None:
        g = g * weight(r)
    wg = g * GL_W[None, :]
    integral = half * wg.sum(axis=1)
    s = wg.sum(axis=1)
    centroid = np.where(s > 0, (wg * r).sum(axis=1) / np.where(s > 0, s, 1.0), mid)
    return integral, centroid


def add_volume_rows(rows, template, beam_fraction, hit_beam, hit_time_s, hit_fraction, gate):
    """rows[p] += template × (the fraction of beam p still unobstructed at each bin): F_p minus the sub-rays
    that hit a surface at or before the bin (their volume behind the surface is hidden).  Bin-level truncation
    (the pulse-convolved tail of the hidden volume within one pulse width of a surface is cut at the bin).
    ``template``: (n_bins,) for every beam, or (n, n_bins), one per beam (per-pixel overlap)."""
    n, nb = rows.shape
    if not np.any(template):
        return
    k = np.floor((np.asarray(hit_time_s) - gate.gate_start_s) / gate.bin_width_s)
    ok = k < nb
    kk = np.clip(k[ok], 0, nb - 1).astype(np.int64)
    # the hidden fraction per (beam, bin): one bincount (sums in input order, as np.add.at) and in-place passes
    vis = np.bincount(np.asarray(hit_beam, np.int64)[ok] * nb + kk, weights=np.asarray(hit_fraction, np.float64)[ok],
                      minlength=n * nb).reshape(n, nb).astype(np.float64, copy=False)  # no hits: bincount gives int
    np.cumsum(vis, axis=1, out=vis)
    np.subtract(np.asarray(beam_fraction, np.float64)[:, None], vis, out=vis)
    np.maximum(vis, 0.0, out=vis)
    vis *= template if template.ndim == 2 else template[None, :]  # (n, nb): each beam's own template
    rows += vis if rows.dtype == vis.dtype else vis.astype(rows.dtype)


# ------------------------------------------------------------------------------------------------------------
# Discrete scatterers
# ------------------------------------------------------------------------------------------------------------
@dataclass
class Drops:
    """Drawn particles, sorted by (beam, range): beam index, range (m), diameter (mm), and a uniform number
    ``u`` in [0, 1) that places the drop inside its beam (which sub-ray's cell it is in)."""

    beam: np.ndarray
    range_m: np.ndarray
    diameter_mm: np.ndarray
    u: np.ndarray

    def __len__(self):
        return len(self.beam)

    def take(self, sel) -> "Drops":
        return Drops(self.beam[sel], self.range_m[sel], self.diameter_mm[sel], self.u[sel])


def expected_drop_count(weather: Weather, omega_sr, r_lo_m, r_hi_m):
    """Mean number of particles (D ≥ D_min) in a cone of solid angle Ω between r_lo and r_hi: n Ω (r_hi³ − r_lo³)/3."""
    if r_hi_m <= r_lo_m:
        return 0.0
    return weather.drop_density_per_m3 * omega_sr * (r_hi_m ** 3 - r_lo_m ** 3) / 3.0


def draw_drops(rng: np.random.Generator, weather: Weather, n_beams: int, omega_sr: float, r_lo_m: float,
               r_hi_m: float, cut: "DropCut | None" = None) -> Drops:
    """Poisson number of particles in ``n_beams`` cones of solid angle Ω each, uniform in volume (R³ uniform),
    diameters D_min + Exp(1/Λ) (the exponential tail above D_min).  With a :class:`DropCut` of more than one
    shell: the particles of each range shell k above its cut D_k (a Poisson total split multinomially over the
    shells = independent Poisson counts per shell), R³ uniform in the shell, D = D_k + Exp(1/Λ): exactly the
    particles of the brute-force draw that lie above the cut, in distribution."""
    if cut is not None and not cut.is_trivial:
        mu = cut.expected_per_beam() * n_beams
        total = float(mu.sum())
        n = int(rng.poisson(total)) if total > 0 else 0
        shell = np.minimum(np.searchsorted(np.cumsum(mu) / total, rng.random(n), side="right"), len(mu) - 1) \
            if n else np.zeros(0, np.int64)
        beam = rng.integers(0, n_beams, n) if n else np.zeros(0, np.int64)
        lo3, hi3 = cut.edges_m[shell] ** 3, cut.edges_m[shell + 1] ** 3
        rng_m = np.cbrt(lo3 + rng.random(n) * (hi3 - lo3))
        diam = cut.d_cut_mm[shell] + rng.exponential(1.0 / weather.lam, n) if n else np.zeros(0)
        u = rng.random(n)
        order = np.lexsort((rng_m, beam))
        return Drops(beam[order].astype(np.int64), rng_m[order], np.asarray(diam)[order], u[order])
    mean = expected_drop_count(weather, omega_sr, r_lo_m, r_hi_m) * n_beams
    n = int(rng.poisson(mean)) if mean > 0 else 0
    beam = rng.integers(0, n_beams, n) if n else np.zeros(0, np.int64)
    r3 = r_lo_m ** 3 + rng.random(n) * (r_hi_m ** 3 - r_lo_m ** 3)
    rng_m = np.cbrt(r3)
    diam = weather.d_min_mm + rng.exponential(1.0 / weather.lam, n) if n else np.zeros(0)
    u = rng.random(n)
    order = np.lexsort((rng_m, beam))
    return Drops(beam[order].astype(np.int64), rng_m[order], np.asarray(diam)[order], u[order])


def drop_returns(drops: Drops, beam_fraction, omega_sr, energy_scale_jm2, aperture_r2, alpha_per_m,
                 lidar_ratio_sr, overlap: Overlap):
    """(energy J (W2), shadowed fraction f) of each drop, for beams of energy fraction ``beam_fraction``."""
    area = 0.25 * np.pi * (drops.diameter_mm * 1e-3) ** 2
    r = drops.range_m
    f = np.minimum(1.0, area / (omega_sr * r * r))
    e = (energy_scale_jm2 * np.asarray(beam_fraction)[drops.beam] * f * (2.0 / lidar_ratio_sr) * overlap(r)
         * two_way_transmission(alpha_per_m, r) / (r * r + aperture_r2))
    return e, f


def visible_drops(drops: Drops, ray_beam, ray_weight, ray_range_m):
    """Which drops are in front of the surface of the sub-ray cell they fall in.  Rays sorted by beam; a drop is in
    the sub-ray whose cumulative weight interval holds u × (the beam's total weight); a missed ray has range inf."""
    if len(drops) == 0:
        return np.zeros(0, bool)
    beam = np.asarray(ray_beam, np.int64)
    order = np.argsort(beam, kind="stable")
    beam = beam[order]
    w = np.asarray(ray_weight, np.float64)[order]
    cum = np.cumsum(w)
    nb = int(max(beam.max() + 1 if len(beam) else 0, drops.beam.max() + 1))
    total = np.bincount(beam, weights=w, minlength=nb)
    first = np.searchsorted(beam, np.arange(nb), side="left")
    start = np.concatenate([[0.0], cum])[first]
    target = start[drops.beam] + drops.u * total[drops.beam]
    ray = np.minimum(np.searchsorted(cum, target, side="right"), len(cum) - 1)
    rr = np.asarray(ray_range_m, np.float64)[order][ray]
    rr = np.where(np.isfinite(rr), rr, np.inf)
    return (drops.range_m < rr) & (beam[ray] == drops.beam)


def shadow_factors(drops: Drops, shadow, query_beam, query_range_m):
    """Π (1 − f) over the drops of the same beam nearer than each query (surface hit or drop); drops sorted by
    (beam, range).  A drop does not shadow itself."""
    q_beam = np.asarray(query_beam, np.int64)
    q_r = np.asarray(query_range_m, np.float64)
    if len(drops) == 0 or len(q_beam) == 0:
        return np.ones(len(q_beam))
    log_t = np.log1p(-np.minimum(shadow, 1.0 - 1e-16))  # a fully shadowed beam: 1e-16 left
    cum = np.concatenate([[0.0], np.cumsum(log_t)])
    span = float(max(np.max(drops.range_m), np.max(np.where(np.isfinite(q_r), q_r, 0.0)))) * 2.0 + 1.0
    key = drops.beam * span + drops.range_m
    q_key = q_beam * span + np.where(np.isfinite(q_r), q_r, span * 0.5)
    start = np.searchsorted(drops.beam, q_beam, side="left")
    stop = np.searchsorted(key, q_key, side="left")
    return np.exp(cum[stop] - cum[start])


def atmosphere_echo_mask(echo_beam, echo_range_m, hit_beam, hit_range_m, tolerance_m):
    """True for an echo with no surface hit of its beam within ``tolerance_m``: a return of the atmosphere."""
    e_b = np.asarray(echo_beam, np.int64)
    e_r = np.asarray(echo_range_m, np.float64)
    if len(e_b) == 0:
        return np.zeros(0, bool)
    h_b = np.asarray(hit_beam, np.int64)
    h_r = np.asarray(hit_range_m, np.float64)
    if len(h_b) == 0:
        return np.ones(len(e_b), bool)
    span = float(max(np.nanmax(np.abs(e_r)), np.max(h_r))) * 4.0 + 4.0 * tolerance_m + 1.0
    key = np.sort(h_b * span + h_r)
    q = e_b * span + e_r
    i = np.searchsorted(key, q)
    near = np.full(len(q), np.inf)
    for j in (i - 1, i):
        ok = (j >= 0) & (j < len(key))
        near[ok] = np.minimum(near[ok], np.abs(key[j[ok]] - q[ok]))
    return ~(near <= tolerance_m)



# ------------------------------------------------------------------------------------------------------------
# Detectability cut: only the drops that can matter are drawn, the others' mean joins the continuum
# ------------------------------------------------------------------------------------------------------------
#: A drop that hides less than this fraction of its beam (and is below the photo-electron cut) is not drawn: its
#: mean shadow joins the extinction (the lost variance of the beam's transmission is ≤ this × its mean loss).
DROP_SHADOW_CUT = 0.01
#: Range shells of the cut: geometric, this ratio between edges; the cut of a shell is the smallest of the ideal
#: cut sampled at this many ranges across it (the cut is then a piecewise constant: the split stays exact).
CUT_SHELL_RATIO = 1.05
CUT_SAMPLES = 9
#: Points per shell of the tabulated optical depth of the particles (interpolated linearly between them).
TAU_GRID = 64


def _g_moment(k: int, lam: float, x):
    """G_k(x) = ∫_x^∞ D^k e^(−ΛD) dD for k = 0, 2 (G(∞) = 0)."""
    x = np.asarray(x, np.float64)
    fin = np.isfinite(x)
    xs = np.where(fin, x, 0.0)
    e = np.exp(-lam * xs)
    g = e / lam if k == 0 else e * (xs * xs / lam + 2.0 * xs / lam ** 2 + 2.0 / lam ** 3)
    return np.where(fin, g, 0.0)


def drop_cross_section_per_m(n0, lam, d_lo_mm, d_hi_mm, omega_sr, range_m):
    """σ(R) = ∫_{D_lo}^{D_hi} N(D) min(A(D), Ω R²) dD (1/m), A = πD²/4: the mean fraction of a beam of solid
    angle Ω that the particles between D_lo and D_hi in the slab [R, R + dR] hide, per metre (a particle larger
    than the beam's cross-section Ω R² hides all of it).  Also (2/S)·σ is their backscatter per metre and
    steradian of the beam (W2 summed).  Broadcasts over D_hi and R; D_hi may be inf."""
    r = np.asarray(range_m, np.float64)
    d_hi = np.broadcast_to(np.asarray(d_hi_mm, np.float64), r.shape) if np.ndim(d_hi_mm) else np.full(r.shape,
                                                                                                       float(d_hi_mm))
    beam_area = omega_sr * r * r
    d_star = 2e3 * np.sqrt(beam_area / np.pi)          # mm: A(D*) = Ω R²
    hi1 = np.minimum(d_hi, np.maximum(d_lo_mm, d_star))
    lo2 = np.maximum(d_lo_mm, np.minimum(d_star, d_hi))
    part1 = 0.25e-6 * np.pi * (_g_moment(2, lam, d_lo_mm) - _g_moment(2, lam, hi1))
    part2 = beam_area * (_g_moment(0, lam, lo2) - _g_moment(0, lam, d_hi))
    return n0 * np.maximum(part1 + part2, 0.0)


@dataclass(frozen=True)
class DropCut:
    """The detectability cut of the discrete particles (docs/theory.md §14): range shells [edges[k], edges[k+1]]
    between r_lo and r_hi, each with the diameter D_k ≥ D_min above which its particles are drawn one by one
    (inf: none).  The particles between D_min and D_k are not drawn: their mean return joins the volume
    backscatter (:meth:`beta_profile`) and their mean shadow the extinction (:meth:`mean_shadow`).  Both parts
    are Poisson processes on disjoint sets, so the mean of every return is that of the brute-force draw."""

    edges_m: np.ndarray
    d_cut_mm: np.ndarray
    omega_sr: float
    n0: float
    lam: float
    d_min_mm: float
    lidar_ratio_sr: float
    aperture_r2: float

    @property
    def is_trivial(self) -> bool:
        """Every shell's cut is D_min: the brute-force draw."""
        return bool(np.all(self.d_cut_mm <= self.d_min_mm))

    def expected_per_beam(self):
        """Mean number of drawn particles per beam in each shell: n(D ≥ D_k) Ω (r_{k+1}³ − r_k³)/3."""
        e = self.edges_m
        dens = np.where(np.isfinite(self.d_cut_mm),
                        self.n0 / self.lam * np.exp(-self.lam * np.where(np.isfinite(self.d_cut_mm),
                                                                         self.d_cut_mm, 0.0)), 0.0)
        return dens * self.omega_sr * (e[1:] ** 3 - e[:-1] ** 3) / 3.0

    def _shell_cut(self, r):
        k = np.clip(np.searchsorted(self.edges_m, r, side="right") - 1, 0, len(self.d_cut_mm) - 1)
        inside = (r >= self.edges_m[0]) & (r <= self.edges_m[-1])
        return np.where(inside, self.d_cut_mm[k], self.d_min_mm)

    def sigma_sub(self, range_m):
        """σ of the undrawn particles (D_min ≤ D < D_k) at each range; 0 outside [r_lo, r_hi]."""
        r = np.asarray(range_m, np.float64)
        return drop_cross_section_per_m(self.n0, self.lam, self.d_min_mm, self._shell_cut(r), self.omega_sr, r)

    def sigma_all(self, range_m):
        """σ of every particle ≥ D_min (drawn or not) at each range in [r_lo, r_hi]; 0 outside."""
        r = np.asarray(range_m, np.float64)
        inside = (r >= self.edges_m[0]) & (r <= self.edges_m[-1])
        return np.where(inside, drop_cross_section_per_m(self.n0, self.lam, self.d_min_mm, np.inf, self.omega_sr,
                                                         r), 0.0)

    def _tau_table(self, sigma):
        """(grid, ∫_{r_lo}^{grid} σ dr): :data:`TAU_GRID` points per shell, each interval integrated by 16-point
        Gauss–Legendre and cumulated."""
        x, w = np.polynomial.legendre.leggauss(16)
        lo, hi = self.edges_m[:-1], self.edges_m[1:]
        t = np.linspace(0.0, 1.0, TAU_GRID + 1)[:-1]
        grid = np.append((lo[:, None] + (hi - lo)[:, None] * t[None, :]).reshape(-1), self.edges_m[-1])
        a, b = grid[:-1], grid[1:]
        nodes = 0.5 * (a + b)[:, None] + 0.5 * (b - a)[:, None] * x[None, :]
        part = 0.5 * (b - a) * (sigma(nodes) * w[None, :]).sum(axis=1)
        return grid, np.concatenate([[0.0], np.cumsum(part)])

    def _tau(self, which: str, range_m):
        """∫_{r_lo}^{R} σ dr (σ_sub or σ_all): the table of :meth:`_tau_table` (computed once per cut), linearly
        interpolated (error ≤ max|σ′| h²/8, h = a shell's width / TAU_GRID: ~1e-7 of τ for 5 % shells; exact where
        σ is constant)."""
        cache = self.__dict__.setdefault("_tau_cache", {})
        if which not in cache:
            cache[which] = self._tau_table(self.sigma_sub if which == "sub" else self.sigma_all)
        grid, tau = cache[which]
        r = np.clip(np.asarray(range_m, np.float64), self.edges_m[0], self.edges_m[-1])
        return np.interp(r, grid, tau)

    def mean_shadow(self, range_m):
        """exp(−∫_{r_lo}^{R} σ_sub): the mean transmission through the undrawn particles nearer than R (for a
        Poisson process E[Π(1 − f_j)] = exp(−Σ E f)); 1 without a cut."""
        if self.is_trivial:
            return np.ones(np.shape(range_m))
        return np.exp(-self._tau("sub", range_m))

    def beta_profile(self, range_m):
        """Backscatter (1/(m sr)) added to the volume at each range: (2/S) σ_sub(R) R²/(R² + r_a²) (W2 summed over
        the undrawn particles) times their mean shadow by every nearer particle ≥ D_min, exp(−∫σ_all)."""
        r = np.asarray(range_m, np.float64)
        s = self.sigma_sub(r)
        if not np.any(s > 0):
            return np.zeros(r.shape)
        return (2.0 / self.lidar_ratio_sr) * s * r * r / (r * r + self.aperture_r2) * np.exp(
            -self._tau("all", r))


def drop_cut(weather: Weather, omega_sr: float, r_lo_m: float, r_hi_m: float, full_beam_pe, cut_pe: float,
             aperture_r2: float) -> DropCut:
    """The :class:`DropCut` of a beam: ``full_beam_pe(R)`` = mean photo-electrons of a particle that hides the
    whole beam at R (W2 with f = 1, the largest beam fraction of the frame); a particle of area A < Ω R² gives
    that × A/(Ω R²).  Drawn: the particles that give at least ``cut_pe`` photo-electrons or hide at least
    :data:`DROP_SHADOW_CUT` of the beam, i.e. A ≥ min(cut_pe/g, DROP_SHADOW_CUT)·Ω R², sampled at
    :data:`CUT_SAMPLES` ranges per shell, the smallest kept.  ``cut_pe`` = 0: one shell, D_min (brute force)."""
    if cut_pe <= 0.0 or r_hi_m <= r_lo_m:
        return DropCut(np.array([r_lo_m, max(r_hi_m, r_lo_m)]), np.array([weather.d_min_mm]), omega_sr, weather.n0,
                       weather.lam, weather.d_min_mm, weather.lidar_ratio_sr, aperture_r2)
    n = max(1, int(math.ceil(math.log(r_hi_m / r_lo_m) / math.log(CUT_SHELL_RATIO))))
    edges = np.geomspace(r_lo_m, r_hi_m, n + 1)
    edges[0], edges[-1] = r_lo_m, r_hi_m
    r = edges[:-1, None] * (edges[1:] / edges[:-1])[:, None] ** np.linspace(0.0, 1.0, CUT_SAMPLES)[None, :]
    g = np.asarray(full_beam_pe(r), np.float64)
    with np.errstate(divide="ignore"):
        frac = np.where(g >= cut_pe, cut_pe / np.where(g > 0, g, 1.0), np.inf)
    area = np.minimum(frac, DROP_SHADOW_CUT) * omega_sr * r * r
    d = 2e3 * np.sqrt(area / np.pi)
    d_cut = np.maximum(weather.d_min_mm, d.min(axis=1))
    return DropCut(edges, d_cut, omega_sr, weather.n0, weather.lam, weather.d_min_mm, weather.lidar_ratio_sr,
                   aperture_r2)
