#!/usr/bin/env python3
"""Compare two run folders file by file: are they the same results?

    python scripts/compare_runs.py RUN_A RUN_B [--ignore KEY ...] [--quiet]

Every file in either folder (recursively) must exist in both and be byte-identical, with four exceptions:

* ``*.json`` files (``metadata.json``, ``sequence.json``) are compared as JSON after dropping, at any depth, the
  keys that record when and with what the run was made: timing (``created_unix_s``, ``wall_time_s``,
  ``time_s`` (the BVH build), ``export_s`` and ``main_thread_s`` (the Blender export), any key ending in
  ``_times_s`` or ``_wall_time_s``), the compiled kernels loaded or compiled (``kernels``) and versions (``software``,
  ``simulator_version``, ``addon_version``), plus any ``--ignore KEY``;
* ``*.npz`` archives are compared member by member (names and the bytes of each ``.npy`` member), because the
  zip container stamps each member with the time it was written;
* ``*.las`` files are compared as header (all fields but the creation day/year and the offset to the points,
  which moves with the length of the JSON record), variable-length records (byte for byte, except the
  simulator's JSON record, compared as JSON like the metadata) and point records (byte for byte);
* ``*.png`` previews are compared as pictures: size, colour mode, the decoded pixels (every value), the text
  chunks (``Software``, ``Title``, ``Description``) and the resolution, not as bytes (how the pixels are
  compressed is not a result: session 32's previews deflate them otherwise than Pillow's ``savefig`` did).

Exit code 0 when the folders hold the same results, 1 when they differ (each difference is printed), 2 on a
usage error.  Used to show that a refactor changes no output (the four README examples, before and after).
"""
from __future__ import annotations

import argparse
import json
import math
import struct
import sys
import zipfile
from pathlib import Path

IGNORED_KEYS = {"created_unix_s", "wall_time_s", "time_s", "export_s", "main_thread_s", "software", "kernels",
                "simulator_version", "addon_version"}
IGNORED_SUFFIXES = ("_times_s", "_wall_time_s")


def _strip(obj, ignored: set[str]):
    if isinstance(obj, dict):
        return {k: _strip(v, ignored) for k, v in obj.items()
                if k not in ignored and not k.endswith(IGNORED_SUFFIXES)}
    if isinstance(obj, list):
        return [_strip(v, ignored) for v in obj]
    return obj


def _json_differences(a, b, path: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            p = f"{path}.{k}" if path else k
            if k not in a or k not in b:
                out.append(f"{p}: only in {'B' if k not in a else 'A'}")
            else:
                out += _json_differences(a[k], b[k], p)
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _json_differences(x, y, f"{path}[{i}]")]
    if a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)):
        return []  # NaN (JSON's NaN, e.g. a statistic of no values) is the same result as NaN
    return [f"{path}: {json.dumps(a)[:80]} != {json.dumps(b)[:80]}"]


def _npz_differences(fa: Path, fb: Path) -> list[str]:
    with zipfile.ZipFile(fa) as za, zipfile.ZipFile(fb) as zb:
        na, nb = sorted(za.namelist()), sorted(zb.namelist())
        if na != nb:
            return [f"members differ: {na} != {nb}"]
        return [f"member {n} differs" for n in na if za.read(n) != zb.read(n)]


#: LAS 1.4 header: (offset, size) of the creation day and year (2 × uint16) and of the offset to point data.
_LAS_DATE = (90, 4)
_LAS_OFFSET_TO_POINTS = (96, 4)
_VLR_HEADER = struct.Struct("<H16sHH32s")


def _las_parts(data: bytes, ignored: set[str]):
    header_size = struct.unpack_from("<H", data, 94)[0]
    (offset_to_points,) = struct.unpack_from("<I", data, _LAS_OFFSET_TO_POINTS[0])
    (n_vlrs,) = struct.unpack_from("<I", data, 100)
    header = bytearray(data[:header_size])
    for start, size in (_LAS_DATE, _LAS_OFFSET_TO_POINTS):
        header[start:start + size] = b"\0" * size
    vlrs, pos = [], header_size
    for _ in range(n_vlrs):
        _, user, record_id, length, _ = _VLR_HEADER.unpack_from(data, pos)
        payload = data[pos + _VLR_HEADER.size:pos + _VLR_HEADER.size + length]
        user = user.rstrip(b"\0").decode("ascii", "replace")
        if user == "LadarSimulator":
            payload = _strip(json.loads(payload), ignored)
        vlrs.append((user, record_id, payload))
        pos += _VLR_HEADER.size + length
    return bytes(header), vlrs, data[offset_to_points:]


def _las_differences(fa: Path, fb: Path, ignored: set[str]) -> list[str]:
    (ha, va, pa), (hb, vb, pb) = _las_parts(fa.read_bytes(), ignored), _las_parts(fb.read_bytes(), ignored)
    out = [] if ha == hb else ["header differs"]
    if [v[:2] for v in va] != [v[:2] for v in vb]:
        out.append(f"records differ: {[v[:2] for v in va]} != {[v[:2] for v in vb]}")
    else:
        for (user, rid, x), (_, _, y) in zip(va, vb):
            if isinstance(x, bytes):
                out += [] if x == y else [f"record {user}/{rid} differs"]
            else:
                out += [f"record {user}/{rid}: {d}" for d in _json_differences(x, y)]
    return out + ([] if pa == pb else ["point records differ"])


def _png_differences(fa: Path, fb: Path) -> list[str]:
    """The differences between two PNGs as pictures (size, mode, pixels, text chunks, resolution)."""
    import numpy as np
    from PIL import Image

    with Image.open(fa) as ia, Image.open(fb) as ib:
        pa, pb = np.asarray(ia), np.asarray(ib)
        out = []
        if (ia.size, ia.mode) != (ib.size, ib.mode):
            return [f"picture differs ({ia.size[0]}x{ia.size[1]} {ia.mode} vs {ib.size[0]}x{ib.size[1]} {ib.mode})"]
        if not np.array_equal(pa, pb):
            n = int(np.any((pa != pb).reshape(pa.shape[0], pa.shape[1], -1), axis=2).sum())
            out.append(f"pixels differ ({n} of {pa.shape[0] * pa.shape[1]})")
        if dict(ia.text) != dict(ib.text):
            keys = sorted(k for k in set(ia.text) | set(ib.text) if ia.text.get(k) != ib.text.get(k))
            out.append(f"text chunks differ ({', '.join(keys)})")
        if ia.info.get("dpi") != ib.info.get("dpi"):
            out.append(f"resolution differs ({ia.info.get('dpi')} vs {ib.info.get('dpi')})")
    return out


def compare(run_a: Path, run_b: Path, ignored: set[str]) -> tuple[list[str], int]:
    """(differences, number of files compared)."""
    files_a = {p.relative_to(run_a).as_posix() for p in run_a.rglob("*") if p.is_file()}
    files_b = {p.relative_to(run_b).as_posix() for p in run_b.rglob("*") if p.is_file()}
    diffs = [f"{f}: only in A" for f in sorted(files_a - files_b)]
    diffs += [f"{f}: only in B" for f in sorted(files_b - files_a)]
    common = sorted(files_a & files_b)
    for rel in common:
        fa, fb = run_a / rel, run_b / rel
        if rel.endswith(".json"):
            ja = _strip(json.loads(fa.read_text()), ignored)
            jb = _strip(json.loads(fb.read_text()), ignored)
            diffs += [f"{rel}: {d}" for d in _json_differences(ja, jb)]
        elif rel.endswith(".npz"):
            diffs += [f"{rel}: {d}" for d in _npz_differences(fa, fb)]
        elif rel.endswith(".las"):
            diffs += [f"{rel}: {d}" for d in _las_differences(fa, fb, ignored)]
        elif rel.endswith(".png"):
            diffs += [f"{rel}: {d}" for d in _png_differences(fa, fb)]
        elif fa.read_bytes() != fb.read_bytes():
            diffs.append(f"{rel}: bytes differ ({fa.stat().st_size} vs {fb.stat().st_size} bytes)")
    return diffs, len(common)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_a", type=Path)
    ap.add_argument("run_b", type=Path)
    ap.add_argument("--ignore", action="append", default=[], metavar="KEY",
                    help="another JSON key to leave out of the comparison (repeatable)")
    ap.add_argument("--quiet", action="store_true", help="print only the verdict line")
    args = ap.parse_args(argv)
    for d in (args.run_a, args.run_b):
        if not d.is_dir():
            print(f"compare_runs: error: {d} is not a folder", file=sys.stderr)
            return 2
    diffs, n = compare(args.run_a, args.run_b, IGNORED_KEYS | set(args.ignore))
    if not args.quiet:
        for d in diffs:
            print(d)
    verdict = "identical" if not diffs else f"{len(diffs)} difference(s)"
    print(f"{args.run_a} vs {args.run_b}: {n} common files, {verdict}")
    return 0 if not diffs else 1


if __name__ == "__main__":
    sys.exit(main())
