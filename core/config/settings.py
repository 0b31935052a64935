"""Typed, validated simulation settings (paper §3.1: scene, laser source, atmosphere, receiver).

Every numeric setting is declared with :func:`setting`, which records its SI unit, its allowed range and a
one-line physical description.  The same metadata drives

* :func:`validate` — a bad value raises :class:`ConfigError` naming the field, the value and the range;
* the versioned JSON/TOML config file (:func:`config_to_dict`, :func:`config_from_dict`);
* the Blender properties, which ``ladar_addon`` generates 1:1 from these dataclasses.

All values are SI (metres, seconds, joules, radians).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any


SCHEMA_VERSION = 1

#: Supported sensor system types (paper §2): 3D flash (§2.3), time-of-flight scanner (§2.1), burst
#: illumination / gated viewing (§2.2) and range profiler (§5.3).
SYSTEM_TYPES = ("flash", "scanner", "gated", "profiler")


#: Units the Blender panels show a setting in (``panel_unit``), other than its SI unit: unit → (SI unit, power of
#: ten).  A panel value v means v × 10^power SI units; the add-on converts with decimal arithmetic
#: (``ladar_addon.fields.FieldMap``), so a value typed in the panel reaches the core exactly.  Config files,
#: metadata.json and the core stay in SI.
PANEL_UNITS = {
    "ns": ("s", -9), "s": ("s", 0),
    "fJ": ("J", -15), "µJ": ("J", -6),
    "mrad": ("rad", -3),
    "nm": ("m", -9),
    "pA": ("A", -12), "nA": ("A", -9),
    "1/km": ("1/m", -3),
    "kHz": ("Hz", 3), "Hz": ("Hz", 0),
    "×1e-14 m^-2/3": ("m^-2/3", -14),
    "photons/s": ("1/s", 0),
    "e⁻": ("e-", 0),
    "1/sr": ("1/sr", 0),
    "MiB": ("B", None),  # binary (2**20 bytes), stored as whole MiB: ladar_addon.fields converts it
    "counts": ("", 0), "bits": ("", 0), "bins": ("", 0),
}


def panel_unit(meta: dict) -> str:
    """The unit the Blender panels show a setting in: its ``panel_unit``, else metres for a DISTANCE (the scene's
    length unit), degrees for an ANGLE (the scene's rotation unit), none for a FACTOR, else its SI unit."""
    if meta.get("panel_unit"):
        return meta["panel_unit"]
    subtype = meta.get("subtype") or "NONE"
    return {"DISTANCE": "m", "ANGLE": "°", "FACTOR": ""}.get(subtype, meta.get("unit") or "")


def setting(default, *, lo=None, hi=None, lo_open=False, hi_open=False, unit="", doc="", choices=None,
            subtype="NONE", label="", panel_unit="", choice_labels=None):
    """A dataclass field carrying its allowed range, SI unit and physical description.

    ``subtype`` is the Blender property subtype used by the add-on (DISTANCE, ANGLE, ...); ``label`` is the name a
    person reads in the panels ("Pulse Energy"), ``panel_unit`` the unit the panels show the value in (a key of
    :data:`PANEL_UNITS`; empty: the SI unit, or the Blender unit of the subtype: the scene's length unit for
    DISTANCE, degrees for ANGLE) and ``choice_labels`` the readable name of each choice ("PIN photodiode").
    """
    if panel_unit and PANEL_UNITS[panel_unit][0] != unit:
        raise ValueError(f"panel unit {panel_unit!r} is not a unit of {unit!r}")
    if choices and set(choice_labels or ()) != set(choices):
        raise ValueError(f"choice_labels must name every choice of {choices}")
    meta = {"lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open, "unit": unit, "doc": doc,
            "choices": choices, "subtype": subtype, "label": label, "panel_unit": panel_unit,
            "choice_labels": dict(choice_labels) if choice_labels else None}
    return field(default=default, metadata=meta)


# --------------------------------------------------------------------------------------------------------------
# Settings groups
# --------------------------------------------------------------------------------------------------------------
@dataclass
class LaserSettings:
    """Laser source: temporal (pulse) and spatial (beam) energy distribution (paper §3.1)."""

    pulse_energy_j: float = setting(1e-3, lo=0.0, hi=100.0, lo_open=True, unit="J",
                                    doc="Energy of one transmitted pulse leaving the laser",
                                    label="Pulse Energy", panel_unit="µJ")
    wavelength_m: float = setting(1.064e-6, lo=2e-7, hi=1.2e-5, unit="m", subtype="WAVELENGTH",
                                  doc="Laser wavelength in vacuum",
                                  label="Wavelength", panel_unit="nm")
    pulse_shape: str = setting("gaussian", choices=("gaussian", "rectangular"),
                               doc="Temporal pulse shape: Gaussian (FWHM) or rectangular (full width)",
                               label="Pulse Shape",
                               choice_labels={'gaussian': 'Gaussian', 'rectangular': 'Rectangular'})
    pulse_fwhm_s: float = setting(5e-9, lo=1e-12, hi=1e-6, unit="s", subtype="TIME_ABSOLUTE",
                                  doc="Pulse duration: full width at half maximum (Gaussian) or full width "
                                      "(rectangular)",
                                  label="Pulse FWHM", panel_unit="ns")
    beam_profile: str = setting("gaussian", choices=("gaussian", "uniform"),
                                doc="Spatial beam profile: Gaussian TEM00 or uniform over the field of view",
                                label="Beam Profile",
                                choice_labels={'gaussian': 'Gaussian TEM00', 'uniform': 'Uniform'})
    beam_divergence_rad: float = setting(0.02, lo=1e-7, hi=2.0, unit="rad", subtype="ANGLE",
                                         doc="Full-angle beam divergence at the 1/e² intensity points",
                                         label="Beam Divergence", panel_unit="mrad")
    beam_divergence_y_rad: float = setting(0.0, lo=0.0, hi=2.0, unit="rad", subtype="ANGLE",
                                           doc="Elliptical beam (scanner): full-angle divergence at the 1/e² "
                                               "intensity points along the beam's second axis; 0: a circular "
                                               "beam (beam_divergence_rad both ways)",
                                           label="Beam Divergence (2nd Axis)", panel_unit="mrad")
    beam_orientation_rad: float = setting(0.0, lo=-3.141592653589793, hi=3.141592653589793, unit="rad",
                                          subtype="ANGLE",
                                          doc="Elliptical beam (scanner): angle of the beam_divergence_rad axis "
                                              "from the beam's horizontal axis (≈ +X) towards its vertical "
                                              "axis (≈ +Y)",
                                          label="Beam Ellipse Orientation")
    divergence_fills_fov: bool = setting(True, doc="Set the Gaussian 1/e² divergence to the field-of-view "
                                                   "diagonal (ignore beam_divergence_rad)",
                                         label="Divergence Fills Field of View")
    beam_waist_radius_m: float = setting(0.01, lo=1e-4, hi=1.0, unit="m", subtype="DISTANCE",
                                         doc="1/e² radius W0 of the beam leaving the transmitter (turbulence "
                                             "broadening and wander, docs/theory.md §4)",
                                         label="Beam Waist Radius")
    beam_focus_range_m: float = setting(0.0, lo=0.0, hi=1e7, unit="m", subtype="DISTANCE",
                                        doc="Focus range F0 of the transmitted beam; 0 = collimated",
                                        label="Beam Focus Range")


@dataclass
class ReceiverSettings:
    """Receiver geometry and optics (paper §3.1, eq. 3-4).  Monostatic: co-located with the laser."""

    width_px: int = setting(64, lo=1, hi=8192, unit="px", doc="Detector columns",
                            label="Detector Columns")
    height_px: int = setting(64, lo=1, hi=8192, unit="px", doc="Detector rows",
                             label="Detector Rows")
    fov_x_rad: float = setting(0.02, lo=1e-7, hi=2.8, unit="rad", subtype="ANGLE",
                               doc="Full horizontal field of view of the detector array",
                               label="Horizontal Field of View", panel_unit="mrad")
    fov_y_rad: float = setting(0.02, lo=1e-7, hi=2.8, unit="rad", subtype="ANGLE",
                               doc="Full vertical field of view of the detector array",
                               label="Vertical Field of View", panel_unit="mrad")
    subsamples: int = setting(4, lo=1, hi=1024, doc="Sub-resolution rays per pixel side (S×S rays a pixel; "
                                                    "the range profiler's one pixel usually needs 64 or more)",
                              label="Sub-rays per Pixel Side")
    cell_range_spread: bool = setting(True, doc="Spread each sub-ray's return over the round-trip times its cell "
                                                "of the surface spans (tilted, grazing surfaces) instead of one "
                                                "instant: no sub-ray ripple or spurious echoes (docs/performance.md)",
                                      label="Spread Returns over Cell Depth")
    subray_pattern: str = setting("grid", choices=("grid", "stratified", "sobol", "adaptive"),
                                  doc="Where the S×S sub-rays of a pixel go: cell centres (grid), one jittered "
                                      "point per cell (stratified), a scrambled Sobol net (sobol), or Sobol "
                                      "refined where a pixel's rays disagree (adaptive).  Flash, profiler and gated "
                                      "viewing (which refuses adaptive); the scanner uses "
                                      "scanner.beam_subray_rings",
                                  label="Sub-ray Pattern",
                                  choice_labels={'grid': 'Grid', 'stratified': 'Stratified', 'sobol': 'Sobol',
                                                 'adaptive': 'Adaptive'})
    subray_refine: int = setting(4, lo=2, hi=32, doc="Adaptive pattern: pixels whose sub-rays disagree (edges, "
                                                     "several surfaces) are traced again with (refine·S)² rays",
                                 label="Adaptive Refinement")
    aperture_diameter_m: float = setting(0.05, lo=0.0, hi=10.0, lo_open=True, unit="m", subtype="DISTANCE",
                                         doc="Diameter of the receiver optics entrance aperture",
                                         label="Aperture Diameter")
    system_efficiency: float = setting(0.5, lo=0.0, hi=1.0, lo_open=True, subtype="FACTOR",
                                       doc="Transmit × receive optical efficiency η_sys of eq. 3-1",
                                       label="Optical Efficiency")
    filter_bandwidth_m: float = setting(1e-8, lo=1e-12, hi=1e-6, unit="m", subtype="WAVELENGTH",
                                        doc="Full width of the receiver's optical band-pass filter: the band of "
                                            "sunlight (atmosphere.solar_irradiance_w_m2_nm) that reaches the "
                                            "detector",
                                        label="Filter Bandwidth", panel_unit="nm")


@dataclass
class RangeGateSettings:
    """The time window sampled into the waveform (per pixel)."""

    gate_start_s: float = setting(0.0, lo=0.0, hi=1e-3, unit="s", subtype="TIME_ABSOLUTE",
                                  doc="Time after pulse emission at which the first bin opens",
                                  label="Gate Start", panel_unit="ns")
    bin_width_s: float = setting(1e-9, lo=1e-12, hi=1e-6, unit="s", subtype="TIME_ABSOLUTE",
                                 doc="Duration of one waveform time bin",
                                 label="Bin Width", panel_unit="ns")
    n_bins: int = setting(2048, lo=1, hi=1_000_000, doc="Number of time bins in the range gate (the default "
                                                      "2048 bins of 1 ns from 0 s cover 0–307 m)",
                          label="Number of Bins")
    binning: str = setting("table", choices=("table", "exact"),
                           doc="Flash frames with a Gaussian pulse of σ ≥ 1 bin (and ≤ 8 bins; wider pulses are "
                               "binned by the splat method): the pulse ⊛ cell boxes integrated over each bin from "
                               "a precomputed table (table: within 6e-8 of the peak bin of the exact values, "
                               "docs/flash-model.md) or from the pulse's CDF at every bin edge (exact, the "
                               "reference)",
                           label="Waveform Binning",
                           choice_labels={"table": "Tabulated pulse ⊛ box", "exact": "Exact (reference)"})


@dataclass
class DetectionSettings:
    """Echo detection on each pixel's waveform (peak finding with sub-bin interpolation, docs/theory.md §9)."""

    max_echoes: int = setting(3, lo=1, hi=32, doc="Largest number of echoes reported per pixel",
                              label="Maximum Echoes")
    threshold_j: float = setting(0.0, lo=0.0, hi=1.0, unit="J",
                                 doc="Absolute detection threshold on the waveform (energy per bin)",
                                 label="Detection Threshold", panel_unit="fJ")
    relative_threshold: float = setting(0.05, lo=0.0, hi=1.0, subtype="FACTOR",
                                        doc="Echoes weaker than this fraction of the pixel's strongest peak "
                                            "are dropped",
                                        label="Relative Threshold")
    min_dip: float = setting(0.01, lo=0.0, hi=1.0, subtype="FACTOR",
                             doc="Two peaks are separate echoes only if the waveform between them dips by this "
                                 "fraction of the smaller one (0.01: just above the Sparrow limit of two pulses)",
                             label="Minimum Dip Between Echoes")
    interpolation: str = setting("gaussian", choices=("gaussian", "parabolic", "none"),
                                 doc="Sub-bin peak interpolation: 3-point Gaussian, parabolic or none",
                                 label="Peak Interpolation",
                                 choice_labels={'gaussian': 'Gaussian', 'parabolic': 'Parabolic', 'none': 'None'})
    noisy_threshold_mode: str = setting("calibrated", choices=("adaptive", "calibrated", "fixed"),
                                        doc="Noisy receiver: threshold at k_sigma × the waveform's robust noise "
                                            "σ estimated from each pixel's own row (adaptive, CFAR-like), at "
                                            "k_sigma × the σ of the filtered noise computed from the receiver's "
                                            "noise model (calibrated: shot, excess, dark, read and A/D noise "
                                            "through the filter taps, baseline = the noise mean), or at "
                                            "threshold_counts above the baseline (fixed)",
                                        label="Noisy Threshold Mode",
                                        choice_labels={'adaptive': 'Adaptive (k·σ of the row)',
                                                       'calibrated': 'Calibrated (k·σ of the noise model)',
                                                       'fixed': 'Fixed (counts)'})
    k_sigma: float = setting(5.0, lo=0.5, hi=100.0, doc="Noisy receiver: adaptive threshold in noise σ",
                             label="Adaptive Threshold (σ)")
    threshold_counts: float = setting(0.0, lo=0.0, hi=1e12,
                                      doc="Noisy receiver: fixed threshold above the baseline (counts)",
                                      label="Fixed Threshold", panel_unit="counts")
    signal_free_bins: str = setting("statistical", choices=("per_bin", "statistical"),
                                    doc="Noisy receiver: simulate every bin (per_bin, the reference) or only the "
                                        "stretches with signal, the false alarms of the signal-free stretches "
                                        "drawn from the filtered noise's statistics (statistical; used when the "
                                        "counts are not kept (run.save_counts), the threshold is calibrated and the "
                                        "noise law is known exactly (A/D on) or Gaussian within 2 % at the "
                                        "threshold, else per_bin: "
                                        "the metadata says which ran)",
                                    label="Signal-Free Bins",
                                    choice_labels={'per_bin': 'Per bin (reference)',
                                                   'statistical': 'Statistical (signal stretches only)'})
    matched_filter: bool = setting(True, doc="Noisy receiver: correlate the waveform with the pulse shape "
                                             "before peak finding",
                                   label="Matched Filter")


@dataclass
class AtmosphereSettings:
    """Atmosphere between sensor and scene (paper §3.4, effects A–E; docs/theory.md §1–6)."""

    extinction_per_m: float = setting(0.0, lo=0.0, hi=1.0, unit="1/m",
                                      doc="Aerosol extinction coefficient σ_atm of eq. 3-1 (one-way); used when "
                                          "visibility_m is 0",
                                      label="Extinction Coefficient", panel_unit="1/km")
    visibility_m: float = setting(0.0, lo=0.0, hi=1e6, unit="m", subtype="DISTANCE",
                                  doc="Meteorological visibility (2 % contrast); when > 0 it sets the "
                                      "extinction at the laser wavelength (0: use extinction_per_m)",
                                  label="Visibility")
    visibility_model: str = setting("kim", choices=("kim", "kruse"),
                                    doc="Visibility-to-extinction model (docs/theory.md §6)",
                                    label="Visibility Model", choice_labels={'kim': 'Kim', 'kruse': 'Kruse'})
    cn2_m_23: float = setting(0.0, lo=0.0, hi=1e-11, unit="m^-2/3",
                              doc="Refractive-index structure constant Cn², constant along the path "
                                  "(0: no turbulence)",
                              label="Turbulence Strength Cn²", panel_unit="×1e-14 m^-2/3")
    beam_broadening: bool = setting(True, doc="A: widen the Gaussian beam to its turbulent short-term "
                                              "(or long-term, without wander) radius",
                                    label="Beam Broadening")
    scintillation: bool = setting(True, doc="B: multiply a random scintillation pattern onto the "
                                            "illumination at the target",
                                  label="Scintillation")
    scintillation_model: str = setting("auto", choices=("auto", "lognormal", "gamma_gamma", "gamma_lognormal"),
                                       doc="Scintillation pdf. auto: with wave_optics statistics gamma × log-normal "
                                           "fitted to SI and σ²_lnI; with paper statistics log-normal (eq. 3-5) in "
                                           "weak turbulence, gamma-gamma in moderate/strong (gamma_lognormal needs "
                                           "wave_optics)",
                                       label="Scintillation Model",
                                       choice_labels={'auto': 'Automatic', 'lognormal': 'Log-normal',
                                                      'gamma_gamma': 'Gamma-gamma',
                                                      'gamma_lognormal': 'Gamma × log-normal'})
    scintillation_statistics: str = setting("wave_optics", choices=("wave_optics", "paper"),
                                            doc="Scintillation statistics (SI, covariance, aperture averaging): "
                                                "wave_optics = tabulated from split-step wave optics (agrees "
                                                "from weak to strong turbulence); paper = the paper's formulas "
                                                "(to reproduce its figures)",
                                            label="Scintillation Statistics",
                                            choice_labels={'wave_optics': 'Wave Optics', 'paper': 'Paper Formulas'})
    inner_scale_m: float = setting(0.0, lo=0.0, hi=0.05, unit="m", subtype="DISTANCE",
                                   doc="Inner scale l0 of the turbulence (modified von Kármán spectrum, "
                                       "typically 1–10 mm; 0: none); used by the wave_optics statistics",
                                   label="Inner Scale")
    outer_scale_m: float = setting(0.0, lo=0.0, hi=1e4, unit="m", subtype="DISTANCE",
                                   doc="Outer scale L0 of the turbulence (0: infinite, else ≥ 1 m; typically "
                                       "1–100 m); recorded in the metadata: the wave-optics table is for L0 = ∞ "
                                       "(its measured effect: docs/atmosphere.md)",
                                   label="Outer Scale")
    return_scintillation: bool = setting(True, doc="B: with scintillation, also the return path (target → "
                                                   "receiver aperture): one aperture-averaged factor per pixel "
                                                   "and pulse",
                                         label="Return-path Scintillation")
    beam_wander: bool = setting(True, doc="D: displace the beam centre randomly per pulse",
                                label="Beam Wander")
    turbulence_blur: str = setting("long", choices=("long", "short", "none"),
                                   doc="E: turbulence MTF blur of the received image (long or short exposure)",
                                   label="Turbulence Blur",
                                   choice_labels={'long': 'Long Exposure', 'short': 'Short Exposure', 'none': 'None'})
    weather: str = setting("none", choices=("none", "haze", "fog", "rain", "snow", "custom"),
                           doc="Returns from the atmosphere itself (docs/atmosphere.md, docs/theory.md §14): haze/fog "
                               "= volume backscatter β = α/S from the visibility; rain/snow = extinction from "
                               "rain_rate_mm_h plus drops/flakes (discrete scatterers ≥ drop_min_diameter_mm, the "
                               "smaller ones as volume); custom = α from extinction/visibility, β given; none = "
                               "extinction only (as before)",
                           label="Weather",
                           choice_labels={'none': 'None (extinction only)', 'haze': 'Haze', 'fog': 'Fog',
                                          'rain': 'Rain', 'snow': 'Snow', 'custom': 'Custom β'})
    rain_rate_mm_h: float = setting(0.0, lo=0.0, hi=300.0, unit="mm/h",
                                    doc="Rain rate (snow: melted-water equivalent) for weather = rain or snow",
                                    label="Precipitation Rate")
    backscatter_per_m_sr: float = setting(0.0, lo=0.0, hi=1.0, unit="1/(m sr)",
                                          doc="Volume backscatter coefficient β for weather = custom",
                                          label="Backscatter Coefficient")
    lidar_ratio_sr: float = setting(18.0, lo=1.0, hi=200.0, unit="sr",
                                    doc="Extinction-to-backscatter ratio S = α/β of the aerosol and of each drop "
                                        "(water fog and drops ≈ 18–20 sr in the near IR)",
                                    label="Lidar Ratio")
    overlap_model: str = setting("geometric", choices=("geometric", "none"),
                                 doc="Transmitter/receiver overlap O(R) of the backscatter: geometric = the "
                                     "fraction of the beam disc inside the receiver field-of-view disc, axes "
                                     "tx_rx_offset_m apart; none = O = 1",
                                 label="Overlap Model", choice_labels={'geometric': 'Geometric', 'none': 'None (O = 1)'})
    tx_rx_offset_m: float = setting(0.05, lo=0.0, hi=10.0, unit="m", subtype="DISTANCE",
                                    doc="Distance between the transmitter and receiver optical axes (biaxial "
                                        "offset; 0 = coaxial)",
                                    label="Transmitter–Receiver Offset")
    tx_rx_offset_angle_deg: float = setting(0.0, lo=-180.0, hi=180.0, unit="deg",
                                            doc="Direction of the transmitter's axis from the receiver's in the "
                                                "sensor frame: the angle from its +x (image right) towards +y "
                                                "(image up); 0 = +x.  Sets which side of a flash field sees more "
                                                "near-range backscatter (docs/theory.md §14 W3)",
                                            label="Transmitter Offset Direction")
    backscatter_min_range_m: float = setting(0.5, lo=0.01, hi=1e4, unit="m", subtype="DISTANCE",
                                             doc="No atmosphere returns nearer than this (the receiver's near field; "
                                                 "the 1/R² form diverges at R = 0)",
                                             label="Backscatter Start Range")
    drop_min_diameter_mm: float = setting(1.0, lo=0.05, hi=10.0, unit="mm",
                                          doc="Rain/snow: particles at least this large are drawn one by one as "
                                              "discrete returns; smaller ones add to the volume backscatter",
                                          label="Smallest Discrete Drop")
    drop_cut_photoelectrons: float = setting(0.01, lo=0.0, hi=1e6, unit="e-",
                                             doc="Rain/snow detectability cut: a drop whose return would give fewer "
                                                 "mean photo-electrons than this (at the frame's largest beam "
                                                 "fraction) and that hides < 1 % of its beam is not drawn one by "
                                                 "one: its mean return joins the volume backscatter and its mean "
                                                 "shadow the extinction (docs/theory.md §14); 0 = draw every drop "
                                                 "≥ drop_min_diameter_mm",
                                             label="Drop Detectability Cut")
    #: Range-layered aerosol (no Blender property: set by config files; the add-on keeps it as JSON on the scene,
    #: ladar_addon/blend_config.py, and shows it read only): one row per layer
    #: [start_m, end_m, extinction_per_m(, backscatter_per_m_sr)] (core/config/tables.py).
    aerosol_layers: list = field(default_factory=list, metadata={
        "unit": "m, m, 1/m[, 1/(m sr)]",
        "allowed": "rows [start in [0, 1e6], end in (start, 1e6], extinction in [0, 1]] or with a 4th column "
                   "[..., backscatter in [0, 1]] in every row, in increasing range and not overlapping, at most 256",
        "doc": "Layers of aerosol at ranges from the sensor (e.g. a fog bank): inside [start_m, end_m) the "
               "extinction α and the backscatter β (without the 4th column α/lidar_ratio_sr) add to the "
               "homogeneous ones; every ray's two-way transmission is exp(−2∫α dR) (surfaces, drops and the "
               "volume backscatter), the backscatter needs weather ≠ none (docs/theory.md §14); empty: homogeneous"})
    solar_irradiance_w_m2_nm: float = setting(0.0, lo=0.0, hi=10.0, unit="W/(m^2 nm)",
                                              doc="Solar spectral irradiance at the laser wavelength on a surface "
                                                  "facing the sun (direct beam): sunlight reflected by the scene "
                                                  "into each pixel adds to the detector's background rate "
                                                  "(docs/theory.md §8; every system, with the noisy "
                                                  "receiver); "
                                                  "0 = no sun (only detector.background_rate_photons_per_s)",
                                              label="Solar Spectral Irradiance")
    sun_elevation_rad: float = setting(0.7853982, lo=-1.5707963267948966, hi=1.5707963267948966,
                                       unit="rad", subtype="ANGLE",
                                       doc="Sun elevation above the world XY plane (world +Z up); ≤ 0: the sun is "
                                           "down and lights nothing (default 45° to the 7 digits a panel keeps)",
                                       label="Sun Elevation")
    sun_azimuth_rad: float = setting(0.0, lo=-6.283185307179586, hi=6.283185307179586, unit="rad",
                                     subtype="ANGLE",
                                     doc="Sun azimuth in the world XY plane, from +X towards +Y",
                                     label="Sun Azimuth")


@dataclass
class DetectorSettings:
    """Detector and read-out electronics (paper Figure 4; docs/theory.md §7, §8; core/physics/receiver/).
    ``mode = "ideal"`` skips every step: the products are those of the noise-free pipeline, bit for bit."""

    mode: str = setting("ideal", choices=("ideal", "noisy"),
                        doc="ideal: no detector effects (noise-free energies); noisy: the full receiver chain",
                        label="Receiver Model", choice_labels={'ideal': 'Ideal', 'noisy': 'Noisy'})
    detector_type: str = setting("apd", choices=("pin", "apd", "geiger"),
                                 doc="PIN (G = 1), linear-mode APD, or Geiger-mode photon counting",
                                 label="Detector Type",
                                 choice_labels={'pin': 'PIN photodiode', 'apd': 'APD', 'geiger': 'Geiger-mode APD'})
    quantum_efficiency: float = setting(0.4, lo=0.0, hi=1.0, lo_open=True, subtype="FACTOR",
                                        doc="Quantum efficiency η (Geiger: photon detection efficiency)",
                                        label="Quantum Efficiency")
    apd_gain: float = setting(100.0, lo=1.0, hi=1e4, doc="Mean APD gain G (ignored for PIN)",
                              label="APD Gain")
    apd_k_eff: float = setting(0.02, lo=0.0, hi=1.0, doc="Effective ionization ratio k_eff (McIntyre F)",
                               label="APD Ionization Ratio")
    dark_current_bulk_a: float = setting(1e-12, lo=0.0, hi=1e-3, unit="A",
                                         doc="Bulk dark current (multiplied by the gain)",
                                         label="Bulk Dark Current", panel_unit="pA")
    dark_current_surface_a: float = setting(1e-9, lo=0.0, hi=1e-3, unit="A",
                                            doc="Surface dark current (not multiplied)",
                                            label="Surface Dark Current", panel_unit="nA")
    background_rate_photons_per_s: float = setting(0.0, lo=0.0, hi=1e18, unit="1/s",
                                                   doc="Background (solar) photon rate per pixel at the "
                                                       "detector, before η",
                                                   label="Background Photon Rate", panel_unit="photons/s")
    read_noise_e: float = setting(300.0, lo=0.0, hi=1e7, unit="e-", doc="RMS read-out noise (Gaussian)",
                                  label="Read Noise", panel_unit="e⁻")
    adc_bits: int = setting(12, lo=1, hi=32, doc="A/D converter resolution",
                            label="ADC Resolution", panel_unit="bits")
    adc_full_scale_e: float = setting(2.048e6, lo=1.0, hi=1e15, unit="e-",
                                      doc="Electrons at A/D full scale (step Δ = full scale / 2**bits)",
                                      label="ADC Full Scale", panel_unit="e⁻")
    adc_offset_counts: int = setting(16, lo=0, hi=2**31, doc="Digital offset (pedestal) added to every sample",
                                     label="ADC Offset", panel_unit="counts")
    speckle_dof: float = setting(0.0, lo=0.0, hi=1e9,
                                 doc="Speckle degrees of freedom M (contrast 1/√M); 0 = no speckle",
                                 label="Speckle Degrees of Freedom")
    speckle_correlated: bool = setting(False, doc="Spatially correlate the speckle with the MTF_speckle "
                                                  "(pupil) spectrum instead of independent pixels",
                                       label="Spatially Correlated Speckle")
    geiger_pulses: int = setting(100, lo=1, hi=10_000_000, doc="Pulses accumulated into a Geiger histogram",
                                 label="Geiger Pulses per Histogram")
    geiger_dead_time_bins: int = setting(1_000_000, lo=0, hi=100_000_000,
                                         doc="Geiger dead time in bins (≥ n_bins: one detection per pulse)",
                                         label="Geiger Dead Time", panel_unit="bins")
    enable_optics_mtf: bool = setting(False, doc="Blur each time slice by the diffraction × pixel MTF",
                                      label="Optics Blur (MTF)")
    optics_pixel_mtf: bool = setting(False, doc="Include the pixel-aperture sinc in MTF_opt (off when the ray "
                                                "tracer already integrates over the pixel)",
                                     label="Pixel Aperture in Optics MTF")
    enable_shot_noise: bool = setting(True, doc="Poisson photon/electron statistics",
                                      label="Shot Noise")
    enable_background: bool = setting(True, doc="Add the background photon rate",
                                      label="Background Light")
    enable_dark_current: bool = setting(True, doc="Add bulk and surface dark current",
                                        label="Dark Current")
    enable_excess_noise: bool = setting(True, doc="APD excess noise (gain fluctuations)",
                                        label="APD Excess Noise")
    enable_read_noise: bool = setting(True, doc="Add Gaussian read-out noise",
                                      label="Read Noise")
    enable_adc: bool = setting(True, doc="A/D conversion to integer counts (else float32 electrons)",
                               label="A/D Conversion")
    threads: int = setting(0, lo=0, hi=256, doc="Worker threads of the receiver chain (0: as run.threads); "
                                                "never changes the result",
                           label="Detector Threads")


@dataclass
class ScannerSettings:
    """Time-of-flight laser scanner (paper §2.1): one beam (or a stack of channels) steered by a scan pattern.

    Scan angles are in the sensor frame (Blender camera frame: −Z forward, +Y up, +X right).  The beam is the
    laser's ``beam_divergence_rad`` sampled by rings of sub-rays; the receiver collects the whole footprint
    through ``receiver.aperture_diameter_m``; each pulse's waveform spans the range gate (``gate``)."""

    pattern: str = setting("raster", choices=("raster", "oscillating", "rotating", "palmer", "risley"),
                           doc="raster: unidirectional lines stacked vertically; oscillating: a sinusoidal "
                               "across-track mirror (along-track from platform motion); rotating: spinning "
                               "multi-channel head about the sensor's +Y axis; palmer: conical scan about −Z; "
                               "risley: rotating wedge prisms (rosette) about −Z",
                           label="Scan Pattern",
                           choice_labels={'raster': 'Raster', 'oscillating': 'Oscillating Mirror',
                                          'rotating': 'Rotating Head', 'palmer': 'Palmer (Conical)',
                                          'risley': 'Risley Prisms (Rosette)'})
    pulse_rate_hz: float = setting(100_000.0, lo=1.0, hi=1e8, unit="Hz",
                                   doc="Pulse repetition frequency (per channel)",
                                   label="Pulse Rate", panel_unit="kHz")
    scan_rate_hz: float = setting(100.0, lo=1e-3, hi=1e6, unit="Hz",
                                  doc="Lines per second (raster), mirror oscillation frequency (oscillating), "
                                      "revolutions per second (rotating, palmer), frames per second (risley)",
                                  label="Scan Rate", panel_unit="Hz")
    scan_width_rad: float = setting(0.5, lo=0.0, hi=6.283185307179586, unit="rad", subtype="ANGLE",
                                    doc="Full across-scan angle (raster, oscillating) or azimuth extent "
                                        "(rotating; 2π = a full turn)",
                                    label="Scan Width")
    scan_height_rad: float = setting(0.5, lo=0.0, hi=3.14159, unit="rad", subtype="ANGLE",
                                     doc="Full vertical extent of the raster lines, or of the rotating head's "
                                         "channels",
                                     label="Scan Height")
    n_lines: int = setting(100, lo=1, hi=1_000_000, doc="Raster: number of scan lines",
                           label="Number of Lines")
    n_channels: int = setting(16, lo=1, hi=1024, doc="Rotating: channels (lasers) spread over scan_height_rad, or "
                                                     "the rows of channel_table",
                              label="Number of Channels")
    cone_half_angle_rad: float = setting(0.26, lo=0.0, hi=1.5, unit="rad", subtype="ANGLE",
                                         doc="Palmer: half angle of the scan cone around −Z (the off-nadir "
                                             "angle in the X–Z plane, across the flight line when X is)",
                                         label="Cone Half Angle")
    cone_half_angle_y_rad: float = setting(0.0, lo=0.0, hi=1.5, unit="rad", subtype="ANGLE",
                                           doc="Palmer: half angle of an elliptic scan cone in the Y–Z plane (along "
                                               "the flight line when Y is); 0 = circular (cone_half_angle_rad)",
                                           label="Cone Half Angle Y")
    duration_s: float = setting(0.0, lo=0.0, hi=3600.0, unit="s", subtype="TIME_ABSOLUTE",
                                doc="Scan duration; 0 = one full pattern (all raster lines, one mirror period, "
                                    "one revolution or azimuth sweep, one risley frame 1/scan_rate_hz)",
                                label="Scan Duration", panel_unit="s")
    beam_subray_rings: int = setting(1, lo=0, hi=16,
                                     doc="Rings of sub-rays across the beam footprint: 0 → 1 ray, 1 → 7, "
                                         "2 → 19 (1 + 3r(r+1)); each carries an equal share of the energy",
                                     label="Sub-ray Rings per Beam")
    motion_samples_per_s: float = setting(1000.0, lo=1.0, hi=1e6, unit="Hz",
                                          doc="How often the add-on samples the sensor's animated pose during "
                                              "the scan (poses are interpolated per pulse)",
                                          label="Pose Samples per Second", panel_unit="Hz")
    return_mode: str = setting("all", choices=("all", "strongest", "last", "dual", "first_n"),
                               doc="Echoes reported per pulse: all detected, the strongest, the last (farthest), "
                                   "dual (strongest and last; the second strongest when they are one echo) or "
                                   "the first n_returns",
                               label="Return Mode",
                               choice_labels={'all': 'All Echoes', 'strongest': 'Strongest', 'last': 'Last',
                                              'dual': 'Dual (Strongest + Last)', 'first_n': 'First N'})
    n_returns: int = setting(2, lo=1, hi=32, doc="Return mode first_n: echoes reported per pulse, nearest first",
                             label="Returns per Pulse")
    range_quantum_m: float = setting(0.0, lo=0.0, hi=10.0, unit="m", subtype="DISTANCE",
                                     doc="Range resolution of the output: ranges rounded to the nearest multiple "
                                         "(e.g. 0.004 m); 0: not rounded",
                                     label="Range Quantum")
    intensity_encoding: str = setting("amplitude", choices=("amplitude", "reflectivity", "intensity8"),
                                      doc="Point intensity: the echo amplitude (J per bin), calibrated "
                                          "reflectivity 0–100 diffuse / 101–255 retro-reflective, or an 8-bit "
                                          "range-compensated intensity 0–255 (ideal detector)",
                                      label="Intensity Encoding",
                                      choice_labels={'amplitude': 'Amplitude (J per Bin)',
                                                     'reflectivity': 'Calibrated Reflectivity (0–255)',
                                                     'intensity8': '8-bit Intensity'})
    pulse_model: str = setting("centroid", choices=("subrays", "centroid"),
                               doc="Ideal receiver, waveforms not saved, clear air, Gaussian pulse: each pulse's "
                                   "waveform as the sum of its sub-rays' tabulated returns (subrays, the "
                                   "reference), or as one tabulated pulse at their energy centroid with its "
                                   "second-moment correction where that is within 1e-4 of the pulse's peak bin "
                                   "of the sum in every bin, the sum elsewhere (centroid: ranges within 1/1000 "
                                   "of the pulse's range resolution; docs/systems.md)",
                               label="Pulse Model",
                               choice_labels={"subrays": "Sub-ray Sum (reference)",
                                              "centroid": "Centroid Pulse"})
    #: Per-channel table of the rotating head (no Blender property: config files and presets; the add-on keeps it
    #: as JSON on the sensor camera, ladar_addon/blend_config.py): one row
    #: [elevation_deg, azimuth_offset_deg, fire_offset_s] per channel (core/config/tables.py).
    channel_table: list = field(default_factory=list, metadata={
        "unit": "deg, deg, s[, 1]", "allowed": "rows [elevation in [-90, 90], azimuth offset in [-360, 360], fire "
                                           "offset in [-1, 1]] or with a 4th column [..., relative pulse energy in "
                                           "[0.001, 1000]] in every row, one row per channel",
        "doc": "Rotating: one row [elevation_deg, azimuth_offset_deg, fire_offset_s] per "
               "channel, replacing the evenly spaced channels (n_channels rows); an optional 4th column "
               "relative_pulse_energy scales that channel's pulse energy (its returns, not the background)"})
    #: ... or the same table read from a CSV file (three columns; an optional header row).
    channel_table_file: str = field(default_factory=str, metadata={
        "unit": "", "allowed": "a path to a CSV file (or empty)", "doc": "Rotating: a CSV file of the channel table (columns elevation_deg, "
                           "azimuth_offset_deg, fire_offset_s, optionally relative_pulse_energy; optional header "
                           "row; '#' comments)"})
    #: Risley prisms (pattern risley), one entry per prism, beam order (core/systems/scan_patterns.py).
    risley_prism_hz: list = field(default_factory=list, metadata={
        "unit": "Hz", "allowed": "numbers in [-1e5, 1e5], one per prism (1 to 8)", "doc": "Risley: rotor frequency of each prism (signed: the sense of rotation)"})
    risley_wedge_deg: list = field(default_factory=list, metadata={
        "unit": "deg", "allowed": "non-zero numbers in [-60, 60], one per prism (1 to 8)", "doc": "Risley: wedge angle of each prism; > 0: the face towards the laser is inclined, "
                              "< 0: the face towards the scene"})
    risley_index: list = field(default_factory=list, metadata={
        "unit": "", "allowed": "numbers in [1, 5], one per prism", "doc": "Risley: refractive index of each prism at the laser wavelength"})
    risley_phase_deg: list = field(default_factory=list, metadata={
        "unit": "deg", "allowed": "numbers in [-360, 360], one per prism, or empty", "doc": "Risley: rotor angle of each prism at t = 0 (empty: all 0)"})
    risley_emitters_deg: list = field(default_factory=list, metadata={
        "unit": "deg", "allowed": "rows [alpha, beta] in [-30, 30], at most 256", "doc": "Risley: one [alpha_deg, beta_deg] row per emitter, the direction of its beam "
                              "entering the prisms (empty: one beam along −Z)"})


@dataclass
class GatedSettings:
    """Burst illumination / gated viewing (paper §2.2, §5.1): a flood-lit camera whose shutter opens
    ``gate_width_s`` long at a delay; a sweep of delays gives range slices (one laser pulse per slice)."""

    first_delay_s: float = setting(6.6e-6, lo=0.0, hi=1e-3, unit="s", subtype="TIME_ABSOLUTE",
                                   doc="Delay after pulse emission at which the first slice's gate opens",
                                   label="First Gate Delay", panel_unit="ns")
    delay_step_s: float = setting(2e-9, lo=1e-12, hi=1e-4, unit="s", subtype="TIME_ABSOLUTE",
                                  doc="Delay increment from one slice to the next",
                                  label="Delay Step", panel_unit="ns")
    n_slices: int = setting(30, lo=1, hi=100_000, doc="Number of slices (gate delays) in the sweep",
                            label="Number of Slices")
    gate_width_s: float = setting(20e-9, lo=1e-12, hi=1e-4, unit="s", subtype="TIME_ABSOLUTE",
                                  doc="Time the shutter stays open (full width at half transmission)",
                                  label="Gate Width", panel_unit="ns")
    shutter_edge_s: float = setting(0.0, lo=0.0, hi=1e-5, unit="s", subtype="TIME_ABSOLUTE",
                                    doc="Linear rise and fall time of the shutter (0: rectangular gate)",
                                    label="Shutter Edge Time", panel_unit="ns")
    range_method: str = setting("centroid", choices=("centroid", "peak", "two_gate"),
                                doc="Range from the slice stack: centroid of the intensity-vs-delay profile "
                                    "around its maximum, its peak fitted with the known slice response, or the "
                                    "two-gate ratio of the strongest pair of adjacent slices (docs/theory.md §9)",
                                label="Range Method",
                                choice_labels={'centroid': 'Centroid', 'peak': 'Peak Fit',
                                               'two_gate': 'Two-gate Ratio'})
    min_signal_j: float = setting(0.0, lo=0.0, hi=1.0, unit="J",
                                  doc="Ideal receiver: pixels whose strongest slice is below this energy give no "
                                      "range",
                                  label="Minimum Signal", panel_unit="fJ")
    min_peak_fraction: float = setting(0.01, lo=0.0, hi=1.0, subtype="FACTOR",
                                       doc="Pixels whose strongest slice is below this fraction of the frame's "
                                           "strongest slice give no range (turbulence-blur tails, stray light; "
                                           "0: off)",
                                       label="Minimum Peak Fraction")
    k_sigma: float = setting(5.0, lo=0.0, hi=100.0,
                             doc="Noisy receiver: pixels whose strongest slice is below k_sigma × the noise σ "
                                 "of a slice give no range (0: off)",
                             label="Noise Threshold (σ)")


@dataclass
class RunSettings:
    """What to compute and how (does not change the physics)."""

    seed: int = setting(0, lo=0, hi=2**63 - 1, doc="Run seed: all random numbers derive from it",
                        label="Seed")
    chunk_rays: int = setting(262_144, lo=1024, hi=100_000_000,
                              doc="Rays traced and processed per chunk (bounds memory)",
                              label="Rays per Chunk")
    threads: int = setting(0, lo=0, hi=256, doc="Worker threads for ray tracing (0: all cores)",
                           label="Ray-tracing Threads")
    save_waveforms: bool = setting(True, doc="Write the per-pixel waveform cube to the run folder",
                                   label="Save Waveforms")
    save_counts: bool = setting(False, doc="Noisy receiver: keep the receiver output of every pixel and bin "
                                           "(counts.npy).  It needs every bin simulated, so the per-bin reference "
                                           "route runs (detection.signal_free_bins); without it the statistical "
                                           "route may serve the echoes and no counts are kept",
                                label="Save Counts")
    max_memory_bytes: int = setting(4 * 2**30, lo=2**20, hi=2**44, unit="B",
                                    doc="Largest waveform cube (bytes) a run may allocate",
                                    label="Memory Limit", panel_unit="MiB")
    max_work_s: float = setting(3600.0, lo=1.0, hi=1e7, unit="s",
                                doc="Longest computing time a run may be estimated to take on this machine (its "
                                    "work at measured rates, over run.threads); a longer run is refused before "
                                    "it starts: raise this to run it anyway",
                                label="Work Limit")


@dataclass
class BRDFSettings:
    """Monostatic BRDF of a material (paper §3.3, eq. 3-3; docs/theory.md §10).

    ``lambertian``: f_r = reflectance/π.  ``steinvall``: f_r = A cos⁻⁶θ exp(−tan²θ/s²) + B cosᵐθ.
    ``table``: a measured f_r(θ) (paper §3.3: measured data where it exists, else eq. 3-3), linear in θ
    between the tabulated angles, the first value below the first angle and the last value beyond the last
    (:func:`core.physics.brdf.table_brdf`).
    """

    model: str = setting("lambertian", choices=("lambertian", "steinvall", "table"),
                         doc="BRDF model: Lambertian, Steinvall (eq. 3-3) or a measured table of f_r vs angle",
                         label="BRDF Model",
                         choice_labels={'lambertian': 'Lambertian', 'steinvall': 'Steinvall',
                                        'table': 'Measured Table'})
    reflectance: float = setting(0.3, lo=0.0, hi=1.0, subtype="FACTOR",
                                 doc="Lambertian hemispherical reflectance ρ_d (f_r = ρ_d/π)",
                                 label="Reflectance")
    specular_a: float = setting(0.0, lo=0.0, hi=1e6, unit="1/sr", doc="Steinvall specular amplitude A",
                                label="Specular Amplitude A", panel_unit="1/sr")
    slope_s: float = setting(0.2, lo=1e-4, hi=10.0, doc="Steinvall rms facet slope s",
                             label="Facet Slope s")
    diffuse_b: float = setting(0.1, lo=0.0, hi=1e3, unit="1/sr", doc="Steinvall diffuse amplitude B",
                               label="Diffuse Amplitude B", panel_unit="1/sr")
    diffuse_m: float = setting(1.0, lo=0.0, hi=100.0, doc="Steinvall diffuse exponent m (0: Lambertian)",
                               label="Diffuse Exponent m")
    table_wavelength_m: float = setting(1.064e-6, lo=2e-7, hi=1.2e-5, unit="m", subtype="WAVELENGTH",
                                        doc="Wavelength at which the BRDF table was measured",
                                        label="Table Wavelength", panel_unit="nm")
    #: Measured table (model "table"): incidence angles in degrees, strictly increasing in [0, 90] ...
    table_angle_deg: list = field(default_factory=list, metadata={
        "unit": "deg", "doc": "Measured table (model table): incidence angles, strictly increasing in [0, 90], "
                              "at least 2"})
    #: ... and the monostatic BRDF f_r at each angle (1/sr), finite and ≥ 0.  At least 2 rows.
    table_brdf_per_sr: list = field(default_factory=list, metadata={
        "unit": "1/sr", "doc": "Measured table: the monostatic BRDF f_r at each angle of table_angle_deg, "
                               "finite and ≥ 0"})


#: Table fields of BRDFSettings (lists; not Blender scalar properties: the add-on stores them as a collection).
BRDF_TABLE_FIELDS = ("table_angle_deg", "table_brdf_per_sr")


#: BRDF used for triangles whose material has no ladar settings (grey Lambertian, 30 %).
DEFAULT_BRDF = BRDFSettings()


@dataclass
class SimulationConfig:
    """All settings of one simulation run, minus the scene geometry and the sensor pose."""

    system_type: str = setting("flash", choices=SYSTEM_TYPES, doc="Sensor system type (paper §2)",
                               label="System Type",
                               choice_labels={'flash': '3D Flash', 'scanner': 'Scanner', 'gated': 'Gated Viewing',
                                              'profiler': 'Range Profiler'})
    laser: LaserSettings = field(default_factory=LaserSettings)
    receiver: ReceiverSettings = field(default_factory=ReceiverSettings)
    gate: RangeGateSettings = field(default_factory=RangeGateSettings)
    scanner: ScannerSettings = field(default_factory=ScannerSettings)
    gated: GatedSettings = field(default_factory=GatedSettings)
    detection: DetectionSettings = field(default_factory=DetectionSettings)
    atmosphere: AtmosphereSettings = field(default_factory=AtmosphereSettings)
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    run: RunSettings = field(default_factory=RunSettings)
    #: BRDF overrides by material name (a sweep can change materials without editing the .blend)
    materials: dict = field(default_factory=dict)


GROUPS = ("laser", "receiver", "gate", "scanner", "gated", "detection", "atmosphere", "detector", "run")


def field_specs(cls) -> list[tuple[str, Any, dict]]:
    """(name, default, metadata) of every plain setting of a settings class: what the add-on turns into
    Blender properties."""
    out = []
    for f in dataclasses.fields(cls):
        if f.default is dataclasses.MISSING:
            continue
        out.append((f.name, f.default, dict(f.metadata)))
    return out


def table_fields(cls) -> tuple[str, ...]:
    """Names of the settings of a settings class that are not plain settings (the list-valued ones such as the
    scanner's channel table and Risley prisms and the atmosphere's aerosol layers, and the channel table's file
    path): config files hold them; the add-on has no Blender property for them and keeps them as JSON
    (ladar_addon/blend_config.py)."""
    return tuple(f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING)


#: The table fields of ScannerSettings (channel table, its file, Risley prisms and emitters).
SCANNER_TABLE_FIELDS = table_fields(ScannerSettings)
