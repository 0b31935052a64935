"""Monostatic BRDF models (paper §3.3, eq. 3-3; docs/theory.md §10): Lambertian, Steinvall, and measured tables.

Paper §3.3: "If the material has measured BRDF data, that is used, otherwise a parameterized version is used
to calculate the reflection according to equation (3-3)."  A measured table (model ``"table"``) holds f_r at
increasing incidence angles θ_i (degrees, 0–90) at one stated wavelength; :func:`table_brdf` evaluates it

* linearly in θ (degrees) between neighbouring rows:  f_r(θ) = f_i + (f_{i+1} − f_i)(θ − θ_i)/(θ_{i+1} − θ_i);
* below the first angle: the first value (the monostatic BRDF is even in θ, so a table starting at θ_0 > 0
  extended symmetrically and interpolated linearly through −θ_0 … θ_0 gives exactly this constant);
* beyond the last angle, up to 90°: the last value (held constant; the received energy still vanishes at
  grazing incidence through the cos θ factor of eq. 3-1).

Linear interpolation keeps f_r ≥ 0 and within the range of the two neighbouring measurements, reproduces the
table exactly at its angles, and adds no overshoot near a narrow specular peak (a cubic would).

:func:`brdf_from_principled` maps Blender's Principled BSDF (base colour, roughness, metallic, IOR) onto a
*starting* Steinvall BRDF; see its docstring for the formula.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..config.settings import BRDFSettings
from ..config.validate import check_brdf_table
from ..errors import ConfigError
from ..jit import kernel


#: Model codes of a packed material (:class:`MaterialTable`).
LAMBERTIAN, STEINVALL, TABLE = 0, 1, 2
_MODEL_CODES = {"lambertian": LAMBERTIAN, "steinvall": STEINVALL, "table": TABLE}


@kernel
def steinvall_at(cos_theta, specular_a, slope_s, diffuse_b, diffuse_m):
    """Steinvall (2000) monostatic BRDF of one ray, paper eq. 3-3, in 1/sr.

    f_r(θ) = A cos⁻⁶θ exp(−tan²θ/s²) + B cosᵐθ.

    The specular term is evaluated as A·exp(−tan²θ/s² − 6 ln cosθ) (docs/theory.md §10) with cosθ clamped to
    [1e-150, 1] and the exponent capped at 700, so grazing incidence gives a finite value (→ 0 for the specular
    lobe) instead of 0·∞.
    """
    c = min(max(cos_theta, 1e-150), 1.0)
    c2 = c * c
    tan2 = max((1.0 - c2) / c2, 0.0)
    specular = 0.0
    if specular_a != 0.0:
        specular = specular_a * math.exp(min(-tan2 / (slope_s * slope_s) - 6.0 * math.log(c), 700.0))
    if diffuse_m == 1.0:  # cᵐ of the common exponents without pow (c¹ = c, c⁰ = 1 exactly; c·c correctly rounded)
        diffuse = c
    elif diffuse_m == 0.0:
        diffuse = 1.0
    elif diffuse_m == 2.0:
        diffuse = c * c
    else:
        diffuse = c ** diffuse_m
    return specular + diffuse_b * diffuse


@kernel(inline=True)
def table_at(cos_theta, angle_deg, brdf_per_sr, first, end):
    """f_r(θ) (1/sr) of one ray on a measured table, rows ``first`` … ``end`` − 1 of ``angle_deg`` (strictly
    increasing) and ``brdf_per_sr``: linear in θ (degrees) between rows, the first value below the first angle,
    the last value beyond the last angle (module docstring); cos θ is clipped to [0, 1].  The arithmetic of
    ``np.interp`` (NumPy 1.26), value for value."""
    theta = math.acos(min(max(cos_theta, 0.0), 1.0)) * (180.0 / math.pi)
    if cos_theta != cos_theta:
        return cos_theta  # NaN in, NaN out (as np.interp)
    last = end - 1
    if not theta < angle_deg[last]:  # at or beyond the last angle
        return brdf_per_sr[last]
    if theta < angle_deg[first]:
        return brdf_per_sr[first]
    lo, hi = first, last  # angle_deg[lo] <= theta < angle_deg[hi]
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if angle_deg[mid] <= theta:
            lo = mid
        else:
            hi = mid
    if theta == angle_deg[lo]:
        return brdf_per_sr[lo]
    slope = (brdf_per_sr[lo + 1] - brdf_per_sr[lo]) / (angle_deg[lo + 1] - angle_deg[lo])
    return slope * (theta - angle_deg[lo]) + brdf_per_sr[lo]


@kernel(inline=True)
def material_brdf_at(model, params, start, angle_deg, brdf_per_sr, material, cos_theta):
    """f_r(θ) (1/sr) of one ray hitting material index ``material`` of a packed :class:`MaterialTable`
    (0 ≤ material < its length: not checked here, see :func:`bad_material`)."""
    code = model[material]
    if code == LAMBERTIAN:
        return params[material, 0]
    if code == TABLE:
        return table_at(cos_theta, angle_deg, brdf_per_sr, start[material], start[material + 1])
    return steinvall_at(cos_theta, params[material, 0], params[material, 1], params[material, 2],
                        params[material, 3])


@kernel
def _evaluate(model, params, start, angle_deg, brdf_per_sr, material, cos_theta, out):
    for i in range(cos_theta.shape[0]):
        if material[i] < 0 or material[i] >= model.shape[0]:
            return i
        out[i] = material_brdf_at(model, params, start, angle_deg, brdf_per_sr, material[i], cos_theta[i])
    return -1


def bad_material(first_bad, material_ids, n_materials):
    """IndexError for the first ray whose material index is out of range, as a kernel reported it (``first_bad``
    ≥ 0: its position; the kernels check each index before using it and stop there)."""
    if first_bad >= 0:
        raise IndexError(f"material index {int(np.reshape(material_ids, -1)[first_bad])} out of range "
                         f"(0 … {n_materials - 1})")


class MaterialTable(NamedTuple):
    """Materials packed for the compiled kernels: per material its model code (LAMBERTIAN, STEINVALL, TABLE),
    four parameters (ρ_d/π, 0, 0, 0 | A, s, B, m | unused) and its table rows angle_deg[start[k]:start[k+1]],
    brdf_per_sr[…] (none for the parametric models)."""

    model: np.ndarray
    params: np.ndarray
    start: np.ndarray
    angle_deg: np.ndarray
    brdf_per_sr: np.ndarray


def material_table(materials) -> MaterialTable:
    """Pack a list of :class:`BRDFSettings` for :func:`material_brdf_at`."""
    n = len(materials)
    model, params, start = np.zeros(n, np.int64), np.zeros((n, 4)), np.zeros(n + 1, np.int64)
    angles, values = [], []
    for k, brdf in enumerate(materials):
        model[k] = _MODEL_CODES[brdf.model]
        if brdf.model == "lambertian":
            params[k, 0] = brdf.reflectance / np.pi
        elif brdf.model == "steinvall":
            params[k] = brdf.specular_a, brdf.slope_s, brdf.diffuse_b, brdf.diffuse_m
        else:
            if len(brdf.table_angle_deg) == 0 or len(brdf.table_angle_deg) != len(brdf.table_brdf_per_sr):
                raise ValueError("a measured BRDF table needs one value per angle, at least one row")
            angles += [float(a) for a in brdf.table_angle_deg]
            values += [float(v) for v in brdf.table_brdf_per_sr]
        start[k + 1] = len(angles)
    return MaterialTable(model, params, start, np.array(angles, np.float64), np.array(values, np.float64))


def _evaluate_table(table: MaterialTable, material_ids, cos_theta):
    c = np.asarray(cos_theta, dtype=np.float64)
    flat = c.reshape(-1)
    ids = np.broadcast_to(np.asarray(material_ids), c.shape).reshape(-1)
    out = np.empty(flat.shape[0])
    bad_material(_evaluate(*table, ids, flat, out), ids, len(table.model))
    return out.reshape(c.shape)


def steinvall_brdf(cos_theta, specular_a, slope_s, diffuse_b, diffuse_m):
    """Steinvall (2000) monostatic BRDF, paper eq. 3-3, in 1/sr, per element of ``cos_theta``
    (:func:`steinvall_at`)."""
    return evaluate_brdf(BRDFSettings(model="steinvall", specular_a=specular_a, slope_s=slope_s,
                                      diffuse_b=diffuse_b, diffuse_m=diffuse_m), cos_theta)


def lambertian_brdf(cos_theta, reflectance):
    """Lambertian BRDF f_r = ρ_d/π (1/sr), independent of angle (docs/theory.md §10)."""
    return evaluate_brdf(BRDFSettings(model="lambertian", reflectance=reflectance), cos_theta)


def table_brdf(cos_theta, angle_deg, brdf_per_sr):
    """f_r(θ) (1/sr) of a measured table: linear in θ (degrees) between rows, the first value below the
    first angle, the last value beyond the last angle (module docstring, :func:`table_at`).  cos θ is clipped
    to [0, 1]."""
    return evaluate_brdf(BRDFSettings(model="table", table_angle_deg=list(angle_deg),
                                      table_brdf_per_sr=list(brdf_per_sr)), cos_theta)


def evaluate_brdf(brdf: BRDFSettings, cos_theta):
    """f_r(θ) for one material's settings, per element of ``cos_theta`` (an array of its shape)."""
    return _evaluate_table(material_table([brdf]), 0, cos_theta)


def evaluate_materials(materials, material_ids, cos_theta):
    """f_r per ray for rays hitting triangles of the given material indices (one compiled pass)."""
    return _evaluate_table(material_table(materials), material_ids, cos_theta)


def directional_hemispherical_reflectance(brdf: BRDFSettings) -> float:
    """ρ_DH(0) at normal incidence (docs/theory.md §10): 4πs²A(1 − e^(−1/s²)) + 4πB/(m + 4) (Steinvall), ρ_d
    (Lambertian).  A physically plausible material has ρ_DH ≤ 1.  Not defined for a measured monostatic
    table (it holds no bistatic information): ValueError."""
    if brdf.model == "table":
        raise ValueError("ρ_DH needs a bistatic BRDF; a monostatic table does not define it")
    if brdf.model == "lambertian":
        return brdf.reflectance
    s2 = brdf.slope_s ** 2
    return 4 * np.pi * s2 * brdf.specular_a * (1 - np.exp(-1 / s2)) + 4 * np.pi * brdf.diffuse_b / (
        brdf.diffuse_m + 4)


def lambertian_equivalent_reflectance(brdf: BRDFSettings, theta_deg) -> np.ndarray:
    """π f_r(θ): the reflectance ρ_d a Lambertian surface needs to return the same energy at incidence θ."""
    return np.pi * evaluate_brdf(brdf, np.cos(np.radians(np.asarray(theta_deg, dtype=np.float64))))


# --------------------------------------------------------------------------------------------------------------
# Measured tables from text files
# --------------------------------------------------------------------------------------------------------------
_WAVELENGTH_RE = re.compile(r"wavelength[^0-9]*?([0-9]+(?:\.[0-9]*)?(?:[eE][-+]?[0-9]+)?)\s*(nm|um|µm|micron|m)\b",
                            re.IGNORECASE)
_WAVELENGTH_UNITS_M = {"nm": 1e-9, "um": 1e-6, "µm": 1e-6, "micron": 1e-6, "m": 1.0}
_SPLIT_RE = re.compile(r"[,;\s]+")


def _parse_float(token: str):
    try:
        return float(token)
    except ValueError:
        return None


def parse_brdf_table(text: str, source: str = "table") -> tuple[list, list, float | None]:
    """Read a measured BRDF table: one row per line, incidence angle (degrees) then f_r (1/sr).

    Columns are separated by commas, semicolons, tabs or spaces.  Empty lines and comment lines (starting
    with ``#``, ``%`` or ``//``) are skipped anywhere; non-numeric header lines are allowed before the first
    row.  A comment or header such as ``# wavelength = 1064 nm`` (units nm, um/µm or m) states the wavelength.

    Returns ``(angle_deg, brdf_per_sr, wavelength_m or None)``, validated with
    :func:`core.config.check_brdf_table`; a bad line or value raises ConfigError naming the file and line.
    """
    angles, values, lines_of_rows = [], [], []
    wavelength_m = None
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip().lstrip("\ufeff")
        if not line:
            continue
        is_comment = line.startswith(("#", "%", "//"))
        tokens = [t for t in _SPLIT_RE.split(line.lstrip("#%/").strip()) if t]
        numbers = [_parse_float(t) for t in tokens]
        if is_comment or not tokens or numbers[0] is None:
            match = _WAVELENGTH_RE.search(line)
            if match and wavelength_m is None:
                wavelength_m = float(match.group(1)) * _WAVELENGTH_UNITS_M[match.group(2).lower()]
            if is_comment or not angles:
                continue  # a comment anywhere, or a header line before the first row
            raise ConfigError(f"{source} line {number}", raw.strip(),
                              "two numbers per row: incidence angle (degrees), BRDF (1/sr)")
        if len(numbers) != 2 or numbers[1] is None:
            raise ConfigError(f"{source} line {number}", raw.strip(),
                              "exactly two numbers per row: incidence angle (degrees), BRDF (1/sr)")
        angles.append(numbers[0])
        values.append(numbers[1])
        lines_of_rows.append(number)
    try:
        check_brdf_table(angles, values)
    except ConfigError as exc:
        index = re.search(r"\[(\d+)\]$", exc.field)
        where = f" (line {lines_of_rows[int(index.group(1))]})" if index else ""
        raise ConfigError(f"{source}: {exc.field}{where}", exc.value, exc.allowed) from None
    if wavelength_m is not None and not 2e-7 <= wavelength_m <= 1.2e-5:
        raise ConfigError(f"{source}: wavelength", wavelength_m, "a wavelength in [2e-07, 1.2e-05] m")
    return angles, values, wavelength_m


def load_brdf_table(path) -> tuple[list, list, float | None]:
    """:func:`parse_brdf_table` of a UTF-8 (or Latin-1) text file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("BRDF table file", str(path), "an existing CSV or text file")
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    return parse_brdf_table(text, path.name)


# --------------------------------------------------------------------------------------------------------------
# A starting BRDF from Blender's Principled BSDF
# --------------------------------------------------------------------------------------------------------------
#: Smallest facet slope the Principled mapping produces (a mirror-smooth surface would need A → ∞).
PRINCIPLED_MIN_SLOPE = 0.01


def brdf_from_principled(base_color_rgb, roughness: float, metallic: float = 0.0, ior: float = 1.5,
                         specular_ior_level: float = 0.5) -> BRDFSettings:
    """A *starting* Steinvall BRDF (eq. 3-3) from Principled BSDF inputs — a visible-light appearance model,
    so the result is a first guess at the laser wavelength, not a measurement.

    With Y = 0.2126 R + 0.7152 G + 0.0722 B the luminance of the linear base colour (clipped to [0, 1]):

    * dielectric Fresnel reflectance at normal incidence F0 = ((n − 1)/(n + 1))² · 2 · specular_ior_level
      (Blender's "Specular IOR Level" 0.5 leaves F0 unchanged), clipped to [0, 1];
    * specular (facet) reflectance ρ_F = (1 − metallic) F0 + metallic Y;
    * diffuse reflectance ρ_d = (1 − metallic)(1 − F0) Y;
    * rms facet slope s = max(roughness², 0.01) (Blender's GGX α = roughness²; Beckmann s ≈ α);
    * A = ρ_F/(4π s²) (Beckmann form, docs/theory.md §10), B = ρ_d/π, m = 0 (Lambertian diffuse lobe).
    """
    rgb = np.clip(np.asarray(base_color_rgb, dtype=np.float64)[:3], 0.0, 1.0)
    luminance = float(np.dot([0.2126, 0.7152, 0.0722], rgb))
    roughness = min(max(float(roughness), 0.0), 1.0)
    metallic = min(max(float(metallic), 0.0), 1.0)
    f0 = min(max(((ior - 1.0) / (ior + 1.0)) ** 2 * 2.0 * specular_ior_level, 0.0), 1.0)
    rho_facet = (1.0 - metallic) * f0 + metallic * luminance
    rho_diffuse = (1.0 - metallic) * (1.0 - f0) * luminance
    slope = max(roughness * roughness, PRINCIPLED_MIN_SLOPE)
    return BRDFSettings(model="steinvall", specular_a=rho_facet / (4.0 * math.pi * slope * slope), slope_s=slope,
                        diffuse_b=rho_diffuse / math.pi, diffuse_m=0.0)
