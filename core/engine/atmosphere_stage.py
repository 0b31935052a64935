"""The atmosphere stage of a frame (paper §3.4, effects A–E), wired from the settings to the systems.

Per frame the turbulence is evaluated at a reference range R_ref, the median range of the pixel-centre
rays that hit the scene (the paper applies one scintillation pattern at the target):

* A  broadening: the Gaussian beam is widened by W_ST/W (short-term radius, when wander is simulated
     separately) or W_LT/W (long-term radius, without wander) at R_ref (docs/theory.md §4); energy conserved;
* B  scintillation: one pattern per pulse, in metres on the plane ⟂ to the line of sight at R_ref, multiplied
     onto the illumination of every sub-ray at (x_tan·R_ref, y_tan·R_ref); where a sub-ray's footprint is
     larger than a scintillation cell, the pattern averaged over the footprint (FootprintAveragedPattern);
* B' return path: the light scattered back by each pixel's footprint reaches the receiver aperture through
     turbulence too.  One unit-mean gamma factor per pixel and pulse with variance
     A_sp(D) · SI_sp · g(p_x/ρ_l) g(p_y/ρ_l): the spherical-wave point-receiver SI, aperture averaging
     A_sp = (1 + 0.33 d²)^(−7/6), d² = kD²/4L (docs/theory.md §3), and the average over the pixel footprint p
     (box_average_variance_factor, correlation radius ρ_l) — small for a resolved diffuse target ("the return
     path is an incoherent extended source"), up to A·SI for footprints below a cell; switch
     ``atmosphere.return_scintillation`` (within B);
* C  extinction: from ``extinction_per_m`` or from the visibility (Kim/Kruse) at the laser wavelength, with
  ``aerosol_layers`` a range-layered one (core.physics.propagation.path_extinction);
* D  wander: the beam centre is displaced by a random offset drawn per pulse with ⟨r_c²⟩ (2.42 form);
* E  blur: the turbulence MTF (spherical-wave r0 at R_ref) applied to every time slice of the received
     waveforms and to the energy image; skipped (and said so) when the MTF at the pixel Nyquist frequency
     exceeds 0.999, i.e. the PSF is far below one pixel.

Random numbers come from SeedSequence([seed, frame, stage]) (:mod:`.rng`) so they do not depend on threads or
chunking.
With Cn² = 0 (or every effect off) nothing here touches the products: the result is bit-identical to a run
without turbulence settings.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..atmosphere import (beam_wander_offsets, beam_wander_variance, derived_turbulence, gaussian_beam_parameters,
                          long_term_beam_radius, make_scintillation_pattern, short_term_beam_radius, turbulence_blur,
                          turbulence_mtf_long)
from ..config.settings import SimulationConfig
from ..jit import kernel
from ..physics.propagation import (FootprintAveragedPattern, draw_return_factor, extinction_record, path_extinction,
                                   return_scintillation_variance, turbulence_model_settings)
from .blocks import worker_threads
from .rng import stage_rng, stage_seed

#: The turbulence blur is skipped when the MTF at the pixel Nyquist frequency exceeds this (PSF ≪ a pixel).
BLUR_NEGLIGIBLE_MTF = 0.999


@dataclass
class FrameAtmosphere:
    extinction_per_m: float = 0.0  # or a LayeredExtinction (atmosphere.aerosol_layers: core.physics.propagation)
    beam_width_scale: float = 1.0
    beam_offset_tan: tuple = (0.0, 0.0)
    pattern: object = None
    reference_range_m: float | None = None
    blur_r0_m: float | None = None
    metadata: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)
    ran: list = field(default_factory=list)

    return_factor: np.ndarray | None = None  # (H, W) return-path factor per pixel (B'), None when off
    subsamples: int = 1

    def scale_by_scintillation(self, e, index, x_tan, y_tan, sub_x, sub_y):
        """e *= the scintillation factor (:meth:`scintillation_at`) of the sub-rays ``index`` of a block, in place:
        the footprint-averaged pattern and the return factor in one compiled pass (the same products), other
        patterns through :meth:`scintillation_at`."""
        if isinstance(self.pattern, FootprintAveragedPattern):
            with_return = self.return_factor is not None
            _scale_by_cells(e, index, sub_x, sub_y, self.pattern.values,
                            self.return_factor if with_return else np.ones((1, 1)), self.subsamples, with_return)
        elif self.pattern is not None:
            e *= self.scintillation_at(x_tan[index], y_tan[index], sub_x[index], sub_y[index])

    def scintillation_at(self, x_tan, y_tan, sub_x, sub_y):
        """Scintillation factor for sub-rays at tan-plane coordinates / sub-ray cells: the outgoing pattern at
        the target times the return-path factor of the sub-ray's pixel."""
        if isinstance(self.pattern, FootprintAveragedPattern):
            out = self.pattern.values[sub_y, sub_x]
        elif self.pattern is None:
            out = np.ones(np.shape(x_tan))
        else:
            r = self.reference_range_m
            out = self.pattern.sample(np.asarray(x_tan) * r, np.asarray(y_tan) * r)
        if self.return_factor is not None:
            s = self.subsamples
            out = out * self.return_factor[np.asarray(sub_y) // s, np.asarray(sub_x) // s]
        return out


@kernel
def _scale_by_cells(e, index, sub_x, sub_y, values, return_factor, s, with_return):
    """e[i] *= values[cell] (× return_factor[cell's pixel] when ``with_return``) for the sub-ray cell of ray index[i]:
    FrameAtmosphere.scintillation_at's footprint-averaged product, in the same order."""
    for i in range(e.shape[0]):
        j = index[i]
        cy, cx = sub_y[j], sub_x[j]
        f = values[cy, cx]
        if with_return:
            f = f * return_factor[cy // s, cx // s]
        e[i] = e[i] * f


def turbulence_switches(config: SimulationConfig) -> dict:
    """Which turbulence effects this run computes, with the reason for each one skipped."""
    atm, laser = config.atmosphere, config.laser
    skipped = {}
    if atm.cn2_m_23 == 0.0:
        for name in ("beam_broadening", "scintillation", "return_scintillation", "beam_wander", "turbulence_blur"):
            skipped[name] = "atmosphere.cn2_m_23 = 0: no turbulence"
        return skipped
    if not atm.beam_broadening:
        skipped["beam_broadening"] = "atmosphere.beam_broadening = false"
    elif laser.beam_profile != "gaussian":
        skipped["beam_broadening"] = "laser.beam_profile = uniform: broadening applies to a Gaussian beam"
    if not atm.scintillation:
        skipped["scintillation"] = "atmosphere.scintillation = false"
    if not atm.beam_wander:
        skipped["beam_wander"] = "atmosphere.beam_wander = false"
    elif laser.beam_profile != "gaussian":
        skipped["beam_wander"] = "laser.beam_profile = uniform: wander applies to a Gaussian beam"
    if not atm.scintillation:
        skipped["return_scintillation"] = "atmosphere.scintillation = false"
    elif not atm.return_scintillation:
        skipped["return_scintillation"] = "atmosphere.return_scintillation = false"
    if atm.turbulence_blur == "none":
        skipped["turbulence_blur"] = "atmosphere.turbulence_blur = none"
    return skipped


def prepare_frame_atmosphere(config: SimulationConfig, det, reference_range_m, frame: int,
                             pulse: int | None = None) -> FrameAtmosphere:
    """Evaluate the atmosphere of one frame: extinction, and the turbulence realisation at R_ref (of one pulse
    of the frame when ``pulse`` is given: gated viewing draws a new realisation per slice)."""
    atm, laser = config.atmosphere, config.laser
    out = FrameAtmosphere(extinction_per_m=path_extinction(config))
    if out.extinction_per_m == 0.0:
        out.skipped["extinction"] = "no extinction (extinction_per_m = 0, no visibility and no aerosol layers)"
    else:
        out.ran.append("extinction")
        out.metadata.update(extinction_record(out.extinction_per_m))
    out.skipped.update(turbulence_switches(config))
    active = [s for s in ("beam_broadening", "scintillation", "beam_wander", "turbulence_blur")
              if s not in out.skipped]
    if not active:
        return out
    r_ref = float(reference_range_m)
    out.reference_range_m = r_ref
    lam = laser.wavelength_m
    focus = laser.beam_focus_range_m if laser.beam_focus_range_m > 0 else np.inf
    derived = derived_turbulence(atm.cn2_m_23, lam, r_ref, wave="spherical",
                                 aperture_diameter_m=config.receiver.aperture_diameter_m,
                                 **turbulence_model_settings(config))
    meta = {"reference_range_m": r_ref, "derived": derived}
    beam = gaussian_beam_parameters(lam, laser.beam_waist_radius_m, r_ref, focus)
    r_c2 = float(beam_wander_variance(atm.cn2_m_23, r_ref, laser.beam_waist_radius_m, focus))
    meta["beam_wander_variance_m2"] = r_c2
    if "beam_broadening" in active:
        w = float(beam["w_m"])
        w_lt = float(long_term_beam_radius(w, derived["rytov_variance_plane"], beam["lam"]))
        radius = float(short_term_beam_radius(w_lt, r_c2, w)) if "beam_wander" in active else w_lt
        out.beam_width_scale = radius / w
        meta.update(free_space_radius_m=w, long_term_radius_m=w_lt, broadened_radius_m=radius,
                    beam_width_scale=out.beam_width_scale)
    if "beam_wander" in active:
        offset_m = beam_wander_offsets(r_c2, stage_rng(config.run.seed, frame, "beam_wander", pulse))
        out.beam_offset_tan = (float(offset_m[0]) / r_ref, float(offset_m[1]) / r_ref)
        meta["beam_wander_offset_m"] = [float(offset_m[0]), float(offset_m[1])]
    if "scintillation" in active:
        seq = stage_seed(config.run.seed, frame, "scintillation", pulse)
        rng = np.random.default_rng(seq)
        sub_pitch_m = (2 * det.half_width_tan * r_ref / (det.width_px * det.subsamples),
                       2 * det.half_height_tan * r_ref / (det.height_px * det.subsamples))
        if min(sub_pitch_m) > derived["cell_radius_m"]:
            out.pattern = FootprintAveragedPattern.draw(det, sub_pitch_m, derived, seq,
                                                        worker_threads(config.run.threads))
            meta["scintillation_pattern"] = out.pattern.params
        else:
            half_x, half_y = det.half_width_tan * r_ref, det.half_height_tan * r_ref
            out.pattern = make_scintillation_pattern((-half_x, half_x, -half_y, half_y), atm.cn2_m_23, lam, r_ref,
                                                     rng, wave="spherical", model=atm.scintillation_model,
                                                     max_grid_px=2048, statistics=atm.scintillation_statistics,
                                                     inner_scale_m=atm.inner_scale_m)
            meta["scintillation_pattern"] = {k: v for k, v in out.pattern.params.items() if k != "derived"}
        if "return_scintillation" not in out.skipped:  # B': the return path through the receiver aperture
            px_m = (2 * det.half_width_tan * r_ref / det.width_px, 2 * det.half_height_tan * r_ref / det.height_px)
            info = return_scintillation_variance(derived, px_m)
            out.return_factor, info["model"] = draw_return_factor(
                (det.height_px, det.width_px), px_m, info,
                stage_rng(config.run.seed, frame, "return_scintillation", pulse))
            out.subsamples = det.subsamples
            meta["return_scintillation"] = info
            out.ran.append("return_scintillation")
    if "turbulence_blur" in active:
        pitch_rad = min(det.pixel_pitch_tan)
        nyquist = 0.5 / pitch_rad
        mtf_nyquist = float(turbulence_mtf_long(nyquist, lam, derived["r0_spherical_m"]))
        meta["blur_mtf_at_nyquist"] = mtf_nyquist
        if mtf_nyquist > BLUR_NEGLIGIBLE_MTF:
            out.skipped["turbulence_blur"] = (f"turbulence MTF at the pixel Nyquist frequency is {mtf_nyquist:.6f} "
                                              f"> {BLUR_NEGLIGIBLE_MTF}: the blur is far below one pixel")
            active.remove("turbulence_blur")
        else:
            out.blur_r0_m = derived["r0_spherical_m"]
            meta["blur_r0_m"] = out.blur_r0_m
    out.ran += active
    out.metadata["turbulence"] = meta
    return out


def blur_cube_and_image(cube, energy_image, det, config: SimulationConfig, r0_m, bins_per_chunk: int = 64):
    """Apply the turbulence MTF blur (E) to every time slice of a (H, W, B) cube in place, and to the energy
    image (returned).  Slices with no energy are left as they are (all zero)."""
    pitch = (2 * det.half_height_tan / det.height_px, 2 * det.half_width_tan / det.width_px)
    kwargs = dict(exposure=config.atmosphere.turbulence_blur, aperture_diameter_m=config.receiver.aperture_diameter_m)
    lam = config.laser.wavelength_m
    occupied = np.flatnonzero(cube.reshape(-1, cube.shape[2]).any(axis=0))
    if len(occupied):
        lo, hi = occupied[0], occupied[-1] + 1
        for a in range(lo, hi, bins_per_chunk):
            b = min(a + bins_per_chunk, hi)
            slab = np.moveaxis(cube[:, :, a:b], 2, 0)
            blurred = turbulence_blur(slab, pitch, lam, r0_m, **kwargs)
            cube[:, :, a:b] = np.maximum(np.moveaxis(blurred, 0, 2), 0.0)
    return np.maximum(turbulence_blur(energy_image, pitch, lam, r0_m, **kwargs), 0.0)
