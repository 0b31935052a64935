"""The sweep file: a versioned TOML (or JSON) description of a parameter sweep, and its expansion into points.

::

    sweep_version = 1
    seed = 2026                 # sweep seed: each task's run.seed derives from it and the point/seed index
    seeds = 8                   # seeds (independent noise/turbulence realisations) per point
    combine = "grid"            # "grid": every combination of the axes; "zip": the i-th value of every axis
    frames = [1]                # scene frames simulated for every point and seed (default: the current frame)
    base = "base.toml"          # optional config file over the base settings (relative to the sweep file)

    [settings]                  # optional fixed settings for every point (a config file's tables)
    detector = { mode = "noisy" }

    [axes]
    "sensor.range_m" = { start = 200, stop = 1000, num = 5 }                      # linear, ends included
    "atmosphere.visibility_m" = [2000, 5000, 20000]                              # a list
    "laser.pulse_energy_j" = { start = 1e-5, stop = 1e-3, num = 3, spacing = "log" }  # log-spaced
    "receiver.width_px" = { start = 16, stop = 64, step = 16 }                   # a step, ends included
    "materials.Paint.reflectance" = [0.1, 0.5]                                   # a material's BRDF setting

An axis names a setting by its dotted path (as in a config file and the error messages), a material's BRDF
setting (``materials.<name>.<field>``), or ``sensor.range_m``: the sensor moved along its line of sight so that
the scene point on its boresight (the centre ray's first hit at the base pose) is that far away.
``run.seed`` cannot be swept (``seeds`` sets the realisations).

Every point's settings are built and validated (:func:`point_configs`) before anything runs: a bad value is
refused with a :class:`~core.errors.ConfigError` naming the setting, the value, what is allowed and the point.
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config.files import config_from_dict, config_to_dict, load_config, read_config_file
from ..config.settings import BRDFSettings, SimulationConfig
from ..config.validate import finite_number
from ..errors import ConfigError

SWEEP_VERSION = 1
COMBINE = ("grid", "zip")
#: The pseudo-setting that moves the sensor along its line of sight (metres to the boresight point).
RANGE_AXIS = "sensor.range_m"
RANGE_LIMITS_M = (0.0, 1e7)
#: Most tasks (points × seeds × frames) one sweep may hold, and most points (each point's settings are built and
#: validated before anything runs, a few ms each on a loaded 2-core machine): the largest sweep accepted starts its
#: first task within 30 s (tests/core/sweep/test_sweep.py; docs/sweeps.md has the times measured).  A sweep of
#: 10⁶ tasks took minutes to plan (issue 31): split it into sweeps of other seeds or axis ranges.
MAX_TASKS = 100_000
MAX_POINTS = 1_000
_TOP_KEYS = ("sweep_version", "seed", "seeds", "combine", "frames", "base", "target", "settings", "axes")
_RANGE_KEYS = ("start", "stop", "num", "step", "spacing")


@dataclass
class Axis:
    name: str          # dotted setting path, e.g. "atmosphere.visibility_m"
    values: list       # the values, in order


@dataclass
class SweepSpec:
    axes: list
    combine: str = "grid"
    seeds: int = 1
    seed: int = 0
    frames: list | None = None      # None: the scene's current frame (the API: the scene's first frame)
    base: Path | None = None        # a config file (absolute path) over the caller's base settings
    settings: dict = field(default_factory=dict)
    source: str = ""                # where the spec came from (file path), for messages
    target: str | None = None       # the material whose detection the figures measure (None: at the image centre)

    @property
    def axis_names(self) -> list:
        return [a.name for a in self.axes]

    def normalized(self) -> dict:
        """What defines the sweep's results (the fingerprint of a sweep folder), JSON-ready."""
        out = {"sweep_version": SWEEP_VERSION, "combine": self.combine, "seeds": self.seeds, "seed": self.seed,
               "frames": self.frames, "settings": self.settings,
               "axes": [[a.name, a.values] for a in self.axes]}
        if self.target is not None:  # (absent when not set: the fingerprints of older sweep folders stay)
            out["target"] = self.target
        return out


# --------------------------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------------------------
def load_sweep(path) -> SweepSpec:
    """Read and check a sweep file (``.toml`` or ``.json``).  Raises ConfigError naming the bad entry."""
    path = Path(path)
    data = read_config_file(path, "sweep file")  # not UTF-8, not JSON/TOML, too deep: one line naming the file
    spec = sweep_from_dict(data, root=path.resolve().parent)
    spec.source = str(path)
    return spec


def _whole(path, value, lo, hi):
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ConfigError(path, value, f"a whole number in [{lo}, {hi}]")
    return value


def sweep_from_dict(data: dict, root: Path | None = None) -> SweepSpec:
    """A SweepSpec from the sweep file's tables (``root``: folder that a relative ``base`` is relative to)."""
    if not isinstance(data, dict):
        raise ConfigError("sweep", type(data).__name__, "a table of sweep entries")
    unknown = sorted(set(data) - set(_TOP_KEYS))
    if unknown:
        raise ConfigError(unknown[0], data[unknown[0]], "a sweep entry: " + ", ".join(_TOP_KEYS))
    version = data.get("sweep_version")
    if version != SWEEP_VERSION:
        raise ConfigError("sweep_version", version, f"{SWEEP_VERSION} (this version of the simulator)")
    seed = _whole("seed", data.get("seed", 0), 0, 2**63 - 1)
    seeds = _whole("seeds", data.get("seeds", 1), 1, 100_000)
    combine = data.get("combine", "grid")
    if combine not in COMBINE:
        raise ConfigError("combine", combine, "one of " + ", ".join(repr(c) for c in COMBINE))
    frames = data.get("frames")
    if frames is not None:
        if isinstance(frames, int) and not isinstance(frames, bool):
            frames = [frames]
        if not isinstance(frames, list) or not frames:
            raise ConfigError("frames", frames, "a frame number or a non-empty list of frame numbers")
        for i, f in enumerate(frames):
            _whole(f"frames[{i}]", f, -1_000_000, 1_000_000)
        if len(set(frames)) != len(frames):
            raise ConfigError("frames", frames, "each frame once")
    base = data.get("base")
    if base is not None:
        if not isinstance(base, str) or not base:
            raise ConfigError("base", base, "the path of a .toml or .json config file")
        try:
            base = Path(base).expanduser()
            if not base.is_absolute() and root is not None:
                base = root / base
            exists = base.is_file()
        except (OSError, ValueError, RuntimeError):  # a name too long, a NUL byte, ~user unknown
            exists = False
        if not exists:
            raise ConfigError("base", str(base), "an existing .toml or .json config file")
    target = data.get("target")
    if target is not None and (not isinstance(target, str) or not target.strip() or len(target) > 1000):
        raise ConfigError("target", target, "the name of a material in the scene (the surface whose detection "
                                            "the sweep measures)")
    settings = data.get("settings", {})
    if not isinstance(settings, dict):
        raise ConfigError("settings", settings, "a table of settings (as in a config file)")
    axes_data = data.get("axes")
    if not isinstance(axes_data, dict) or not axes_data:
        raise ConfigError("axes", axes_data, 'a table of at least one axis, e.g. "atmosphere.visibility_m" = '
                                             '[1000, 5000]')
    axes = [Axis(name, _axis_values(name, spec)) for name, spec in _flatten_axes(axes_data, "")]
    spec = SweepSpec(axes=axes, combine=combine, seeds=seeds, seed=seed, frames=frames, base=base,
                     settings=settings, target=target)
    if combine == "zip":
        n = len(axes[0].values)
        for a in axes[1:]:
            if len(a.values) != n:
                raise ConfigError(f"axes.{a.name}", f"{len(a.values)} values",
                                  f"{n} values, as many as axes.{axes[0].name} (combine = \"zip\")")
    n_pts = n_points(spec)
    if n_pts > MAX_POINTS:
        raise ConfigError("axes", f"{n_pts} points", f"at most {MAX_POINTS} points (combinations of the axes' "
                                                     f"values; split the sweep)")
    n_tasks = n_pts * seeds * len(frames or [0])
    if n_tasks > MAX_TASKS:
        raise ConfigError("axes", f"{n_tasks} tasks", f"at most {MAX_TASKS} points × seeds × frames (split the "
                                                      f"sweep)")
    return spec


def _flatten_axes(table: dict, prefix: str):
    """(dotted name, spec) pairs: a quoted key "a.b" and nested tables a = { b = ... } are the same axis."""
    for key, value in table.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and "start" not in value:
            if not value:
                raise ConfigError(f"axes.{name}", value, "a list of values or a range table {start, stop, num}")
            yield from _flatten_axes(value, name + ".")
        else:
            yield name, value


def _axis_values(name: str, spec) -> list:
    path = f"axes.{name}"
    if name == "run.seed":
        raise ConfigError(path, spec, "not an axis: seeds are set by `seeds` and `seed` (derived per point)")
    if isinstance(spec, list):
        if not spec:
            raise ConfigError(path, spec, "at least one value")
        for i, v in enumerate(spec):
            if isinstance(v, (list, dict)):
                raise ConfigError(f"{path}[{i}]", v, "a number, a string or true/false")
            if isinstance(v, float) and not math.isfinite(v):
                raise ConfigError(f"{path}[{i}]", v, "a finite number")
        if len({json.dumps(v) for v in spec}) != len(spec):
            raise ConfigError(path, spec, "each value once")
        return list(spec)
    if not isinstance(spec, dict):
        raise ConfigError(path, spec, "a list of values or a range table {start, stop, num} / {start, stop, step}")
    unknown = sorted(set(spec) - set(_RANGE_KEYS))
    if unknown:
        raise ConfigError(f"{path}.{unknown[0]}", spec[unknown[0]], "a range entry: " + ", ".join(_RANGE_KEYS))
    for key in ("start", "stop"):
        v = spec.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not finite_number(v):
            raise ConfigError(f"{path}.{key}", v, "a finite number")
    start, stop = float(spec["start"]), float(spec["stop"])
    spacing = spec.get("spacing", "linear")
    if spacing not in ("linear", "log"):
        raise ConfigError(f"{path}.spacing", spacing, "'linear' or 'log'")
    if ("num" in spec) == ("step" in spec):
        raise ConfigError(path, spec, "a range with either num (number of values) or step, not both")
    if "num" in spec:
        num = _whole(f"{path}.num", spec["num"], 1, 100_000)
        if spacing == "log":
            if start <= 0 or stop <= 0:
                raise ConfigError(f"{path}.start", start if start <= 0 else stop,
                                  "start and stop > 0 for spacing = \"log\"")
            values = np.geomspace(start, stop, num)
        else:
            values = np.linspace(start, stop, num)
    else:
        if spacing == "log":
            raise ConfigError(f"{path}.spacing", spacing, "'linear' with step (a log range takes num)")
        step = spec["step"]
        if isinstance(step, bool) or not isinstance(step, (int, float)) or not step > 0 or not finite_number(step):
            raise ConfigError(f"{path}.step", step, "a finite number > 0")
        if stop < start:
            raise ConfigError(f"{path}.stop", stop, f"at least start = {start:g} with a step")
        count = int(math.floor((stop - start) / step * (1 + 1e-12) + 1e-9)) + 1
        if count > 100_000:
            raise ConfigError(f"{path}.step", step, "a step giving at most 100000 values")
        values = start + step * np.arange(count)
    whole = all(isinstance(spec.get(k), int) for k in ("start", "stop", "step") if k in spec)
    out = [float(v) for v in values]
    if whole and spacing == "linear":  # whole ends (pixels, bins, ...): whole values stay integers
        out = [int(v) if v.is_integer() else v for v in out]
    return out


def n_points(spec: SweepSpec) -> int:
    if spec.combine == "zip":
        return len(spec.axes[0].values)
    return int(np.prod([len(a.values) for a in spec.axes]))


def points(spec: SweepSpec) -> list[dict]:
    """The points in order: {axis name: value} (grid: the first axis varies slowest)."""
    names = spec.axis_names
    if spec.combine == "zip":
        combos = zip(*[a.values for a in spec.axes])
    else:
        combos = itertools.product(*[a.values for a in spec.axes])
    return [dict(zip(names, c)) for c in combos]


# --------------------------------------------------------------------------------------------------------------
# Validation of every point
# --------------------------------------------------------------------------------------------------------------
def base_config(spec: SweepSpec, base: SimulationConfig | None = None) -> SimulationConfig:
    """The caller's base settings (default settings if None), then the spec's base file, then its [settings]."""
    cfg = base if base is not None else SimulationConfig()
    if spec.base is not None:
        cfg = load_config(spec.base, base=cfg)
    if spec.settings:
        cfg = config_from_dict(spec.settings, base=cfg)
    return cfg


def _set_path(data: dict, name: str, value, material_brdfs: dict) -> None:
    parts = name.split(".")
    if parts[0] == "materials":
        if len(parts) != 3:
            raise ConfigError(f"axes.{name}", value, "materials.<material name>.<BRDF setting>")
        mats = data.setdefault("materials", {})
        if parts[1] not in mats:
            if parts[1] not in material_brdfs:
                raise ConfigError(f"axes.{name}", parts[1], "the name of a material in the scene: "
                                  + ", ".join(sorted(material_brdfs)))
            mats[parts[1]] = dataclasses.asdict(material_brdfs[parts[1]])
        target, key = mats[parts[1]], parts[2]
    elif len(parts) == 1:
        target, key = data, parts[0]
    elif len(parts) == 2 and isinstance(data.get(parts[0]), dict):
        target, key = data[parts[0]], parts[1]
    else:
        raise ConfigError(f"axes.{name}", value, "a setting path such as atmosphere.visibility_m, "
                                                 "materials.<name>.reflectance or sensor.range_m")
    if key not in target:
        raise ConfigError(f"axes.{name}", value, "a known setting: " + ", ".join(sorted(target)))
    if isinstance(target[key], float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    target[key] = value


def check_range_value(value, where: str = RANGE_AXIS) -> float:
    lo, hi = RANGE_LIMITS_M
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not finite_number(value) \
            or not lo < value <= hi:
        raise ConfigError(where, value, f"a finite number in ({lo:g}, {hi:g}] m")
    return float(value)


def point_configs(spec: SweepSpec, base: SimulationConfig, material_brdfs: dict | None = None) -> list:
    """[(values, SimulationConfig, sensor range or None)] for every point, each validated.

    ``material_brdfs``: {name: BRDFSettings} of the scene's materials (a ``materials.<name>.*`` axis starts from
    the scene's BRDF).  Raises ConfigError naming the setting, the value, the allowed range and the point."""
    material_brdfs = dict(material_brdfs or {})
    base_dict = config_to_dict(base)
    out = []
    for index, values in enumerate(points(spec)):
        data = json.loads(json.dumps(base_dict))
        range_m = None
        try:
            for name, value in values.items():
                if name == RANGE_AXIS:
                    range_m = check_range_value(value)
                else:
                    _set_path(data, name, value, material_brdfs)
            cfg = config_from_dict(data)
        except ConfigError as exc:
            where = ", ".join(f"{k} = {v!r}" for k, v in values.items())
            raise ConfigError(exc.field, exc.value, f"{exc.allowed} (sweep point {index}: {where})") from None
        for name in cfg.materials:
            if not isinstance(cfg.materials[name], BRDFSettings):  # pragma: no cover - config_from_dict builds them
                raise ConfigError(f"materials.{name}", cfg.materials[name], "BRDF settings")
        out.append((values, cfg, range_m))
    return out


# numpy's SeedSequence (M. E. O'Neill's seed_seq_fe): its hash constants, pool size and shift
_SS_INIT_A, _SS_MULT_A, _SS_INIT_B, _SS_MULT_B = 0x43B0D7E5, 0x931E8875, 0x8B51F9DD, 0x58F38DED
_SS_MIX_L, _SS_MIX_R, _SS_SHIFT, _SS_POOL = 0xCA01F9DD, 0x4973F715, 16, 4


def task_seeds(sweep_seed: int, point_indices, seed_indices) -> np.ndarray:
    """:func:`task_seed` of many (point, seed index) pairs at once (int64 array), bit for bit: numpy's
    ``SeedSequence([sweep_seed, p, s]).generate_state(2, np.uint64)[0] >> 1`` computed on arrays (the same uint32
    hashing; the entropy of a sweep seed < 2**64 and indices < 2**32 fits the pool of 4 words, so only the pool's
    first mixing round applies).  A million seeds take about 0.4 s instead of minutes."""
    u = np.uint32
    p = np.asarray(point_indices, dtype=np.int64)
    s = np.asarray(seed_indices, dtype=np.int64)
    if p.shape != s.shape or (p.size and (p.min() < 0 or s.min() < 0 or max(p.max(), s.max()) >= 2**32)):
        raise ValueError("point and seed indices: arrays of one shape, each in [0, 2**32)")
    seed = int(sweep_seed)
    if not 0 <= seed < 2**64:
        raise ValueError("the sweep seed: in [0, 2**64)")
    words = [(seed >> (32 * k)) & 0xFFFFFFFF for k in range(max(1, (seed.bit_length() + 31) // 32))]
    entropy = [np.full(p.shape, w, u) for w in words] + [p.astype(u), s.astype(u)]
    hash_const = [_SS_INIT_A]

    def hashmix(v):
        v = v ^ u(hash_const[0])
        hash_const[0] = (hash_const[0] * _SS_MULT_A) & 0xFFFFFFFF
        v = v * u(hash_const[0])
        return v ^ (v >> u(_SS_SHIFT))

    def mix(x, y):
        r = u(_SS_MIX_L) * x - u(_SS_MIX_R) * y
        return r ^ (r >> u(_SS_SHIFT))

    zero = np.zeros(p.shape, u)
    pool = [hashmix(entropy[i] if i < len(entropy) else zero) for i in range(_SS_POOL)]
    for i_src in range(_SS_POOL):
        for i_dst in range(_SS_POOL):
            if i_src != i_dst:
                pool[i_dst] = mix(pool[i_dst], hashmix(pool[i_src]))
    state, hash_b = [], _SS_INIT_B
    for i in range(2):  # two uint32 words: one uint64 (little-endian)
        v = pool[i] ^ u(hash_b)
        hash_b = (hash_b * _SS_MULT_B) & 0xFFFFFFFF
        v = v * u(hash_b)
        state.append(v ^ (v >> u(_SS_SHIFT)))
    word = state[0].astype(np.uint64) | (state[1].astype(np.uint64) << np.uint64(32))
    return (word >> np.uint64(1)).astype(np.int64)


def task_seed(sweep_seed: int, point_index: int, seed_index: int) -> int:
    """The run seed of (point, seed index): from ``numpy.random.SeedSequence`` of the sweep seed and both indices,
    so it depends on nothing else (not the worker count, not the order tasks run in).  In [0, 2**63 - 1]."""
    state = np.random.SeedSequence([int(sweep_seed), int(point_index), int(seed_index)]).generate_state(2, np.uint64)
    return int(state[0] >> np.uint64(1))
