"""Reading the point clouds users hand to ``detect``: .ply, .pcd, our .npz scenes, fused clouds in MCAP."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.geometry import median_neighbour_distance

CLOUD_SUFFIXES = (".ply", ".pcd", ".npz", ".mcap")
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
"""Metres per unit of the units a cloud may come in."""
BED_SPACING = (0.0001, 0.012, 0.002)
"""A bed cloud's point spacing in metres (median nearest-neighbour distance): from a dense fused
cloud's 0.1 mm to a cloud thinned to 12 mm, typically 2 mm."""
BED_EXTENT = (0.05, 5.0, 0.6)
"""A bed cloud's width in metres (between the 5th and 95th percentiles, so that a wall or a stray
point does not count): from a 5 cm patch to a 5 m bed, typically 0.6 m."""
_PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
              "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


@dataclass(frozen=True)
class LoadedCloud:
    points: np.ndarray
    """(N, 3) float64 metres."""
    in_bed_frame: bool
    """True for our synthetic scenes, which are stored in the bed frame."""
    units: str = "m"
    """The units the file was in (``UNITS``)."""
    spacing: float = 0.0
    """Median nearest-neighbour distance of the points, in the file's units."""
    extent: float = 0.0
    """The cloud's width in the file's units, between the 5th and 95th percentiles."""
    unit_doubt: str | None = None
    """Why no unit makes the cloud a bed, when the units were to be inferred and none did (it is then
    read in metres)."""


def load_cloud(path: Path, units: str = "auto") -> LoadedCloud:
    """A cloud in metres, from a file in ``units`` ("auto": those its spacing and width say, see
    ``infer_units``); raises ValueError with a one-line reason when the file cannot be used."""
    try:
        return _load_cloud(Path(path), units)
    except OSError as error:  # unreadable: permissions, a failing disk
        raise ValueError(f"cannot read {path}: {error.strerror or error}") from None


def _load_cloud(path: Path, units: str) -> LoadedCloud:
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path} does not exist")
    if path.is_dir():
        raise ValueError(f"{path} is a folder, not a cloud file")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path) as data:
                points = np.asarray(data["points"], np.float64)
        except Exception as error:
            raise ValueError(f"{path} is not a mushroom-pose scene (.npz with 'points'): "
                             f"{str(error).splitlines()[0] if str(error) else type(error).__name__}") from None
        in_bed = True
    elif suffix == ".mcap":
        from capture.mcap.reader import read_point_cloud
        from capture.source import SourceError

        try:
            points, _ = read_point_cloud(path)
        except SourceError as error:
            raise ValueError(str(error)) from None
        in_bed = False
    elif suffix == ".pcd" and (points := read_pcd(path)) is not None:
        in_bed = False
    elif suffix in (".ply", ".pcd"):
        import open3d as o3d

        ascii_xyz = _check_ply(path) if suffix == ".ply" else None
        cloud = o3d.io.read_point_cloud(str(path))
        points = np.asarray(cloud.points, np.float64)
        if ascii_xyz is not None:
            _agree_with_open3d(path, points, ascii_xyz)
        if len(points) == 0:
            raise ValueError(f"{path}: the cloud is empty or not a readable {suffix} file")
        in_bed = False
    else:
        raise ValueError(f"{path}: unsupported cloud format {suffix or '(none)'}; "
                         f"use one of {', '.join(CLOUD_SUFFIXES)}")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{path}: expected N x 3 points, got shape {points.shape}")
    _refuse_nonfinite(path, points)
    if len(points) == 0:
        raise ValueError(f"{path}: the cloud is empty")
    spacing, extent = median_neighbour_distance(points, sample=200_000), float(np.max(np.ptp(np.percentile(points, [5, 95], axis=0), axis=0)))
    doubt = None
    if units == "auto":
        units = "m" if in_bed else infer_units(spacing, extent)
        if units is None:
            units, doubt = "m", (f"its points lie {spacing:.3g} units apart over {extent:.3g} units, which is no "
                                 "bed in metres, centimetres or millimetres (--units says which it is)")
    elif units not in UNITS:
        raise ValueError(f"unknown units {units!r}; choose one of auto, {', '.join(UNITS)}")
    return LoadedCloud(points * UNITS[units], in_bed, units, spacing, extent, doubt)


def infer_units(spacing: float, extent: float) -> str | None:
    """The units in which a cloud of this point spacing and width is a bed (``BED_SPACING``,
    ``BED_EXTENT``); of several, the one nearest a typical bed; None when none fits."""
    def log_gap(value: float, typical: float) -> float:
        return float(np.log(value / typical)) ** 2

    fits = [unit for unit, scale in UNITS.items()
            if BED_SPACING[0] <= spacing * scale <= BED_SPACING[1] and BED_EXTENT[0] <= extent * scale <= BED_EXTENT[1]]
    if not fits:
        return None
    return min(fits, key=lambda unit: log_gap(spacing * UNITS[unit], BED_SPACING[2])
               + log_gap(extent * UNITS[unit], BED_EXTENT[2]))


_PCD_TYPES = {"F": "f", "I": "i", "U": "u"}
PCD_HEADER_BYTES = 65536
"""A PCD header ends (at its DATA line) within this many bytes."""


def read_pcd(path: Path) -> np.ndarray | None:
    """The x, y, z (N, 3) of an ASCII or binary PCD file, read here: Open3D, which reads every form,
    takes 0.6 s to import, more than ``detect`` spends on a whole bed. None for the compressed form,
    which is left to Open3D. ValueError with a one-line reason for a file that is no readable PCD."""
    with open(path, "rb") as file:
        data = file.read()
    header, position = {}, 0
    while position < min(len(data), PCD_HEADER_BYTES):
        end = data.find(b"\n", position)
        end = len(data) if end < 0 else end
        words = data[position:end].decode("ascii", "replace").split()
        position = end + 1
        if not words or words[0].startswith("#"):
            continue
        header[words[0].upper()] = words[1:]
        if words[0].upper() == "DATA":
            break
    form = (header.get("DATA") or [""])[0].lower()
    if form == "binary_compressed":
        return None
    try:
        fields = header["FIELDS"]
        sizes = [int(size) for size in header.get("SIZE", ["4"] * len(fields))]
        types = [_PCD_TYPES[kind.upper()] for kind in header.get("TYPE", ["F"] * len(fields))]
        counts = [int(count) for count in header.get("COUNT", ["1"] * len(fields))]
        points = int(header["POINTS"][0]) if "POINTS" in header else int(header["WIDTH"][0]) * int(header["HEIGHT"][0])
        if not len(fields) == len(sizes) == len(types) == len(counts) or form not in ("ascii", "binary"):
            raise ValueError
        columns = [fields.index(axis) for axis in "xyz"]
        record = np.dtype([(f"f{k}", f"<{kind}{size}", (count,)) for k, (kind, size, count)
                           in enumerate(zip(types, sizes, counts))])
        if points < 0 or min(counts) < 1:
            raise ValueError
    except (KeyError, ValueError, IndexError, TypeError):
        raise ValueError(f"{path} is not a readable PCD file (its header lacks or garbles FIELDS, SIZE, TYPE, "
                         "COUNT, POINTS or DATA, or names no x, y, z)") from None
    first = np.cumsum([0] + counts)
    if form == "ascii":
        values = data[position:].split()
        if len(values) < points * first[-1]:
            raise ValueError(f"{path} is cut short: its header lists {points} points of {first[-1]} values but the "
                             f"file holds {len(values)} values")
        try:
            table = np.array(values[:points * first[-1]], np.float64).reshape(points, first[-1])
        except ValueError:
            raise ValueError(f"{path}: a value is not a number; the file is not a readable ASCII PCD") from None
        return table[:, [first[c] for c in columns]]
    if len(data) - position < points * record.itemsize:
        raise ValueError(f"{path} is cut short: its header lists {points} points ({points * record.itemsize} bytes "
                         f"of data) but the file holds {len(data) - position} bytes after its header")
    table = np.frombuffer(data, record, points, position)
    return np.stack([table[f"f{c}"][:, 0] for c in columns], 1).astype(np.float64)


def _check_ply(path: Path) -> np.ndarray | None:
    """ValueError if a PLY is shorter than its header's vertices need: bytes for a binary file, values
    for an ASCII one (a lower bound when other elements come first). Open3D reads a cut-short file
    with only a warning, leaving the missing points unread. For an ASCII file whose first element is
    the vertices, also returns their x, y, z as read here, for ``_agree_with_open3d``."""
    with open(path, "rb") as file:
        head = file.read(65536)
    end = re.search(rb"(?m)^end_header[ \t]*\r?$", head)
    if not head.startswith(b"ply") or end is None:
        return None
    header_bytes = end.end() + 1
    lines = head[:end.start()].decode("ascii", "replace").split("\n")
    formats = [line.split()[1] for line in lines if line.split()[:1] == ["format"] and len(line.split()) > 1]
    vertices, record, names, in_vertex, elements = None, 0, [], False, 0
    for words in (line.split() for line in lines):
        if words[:1] == ["element"] and len(words) == 3:
            if in_vertex:
                break
            elements += 1
            in_vertex = words[1] == "vertex"
            if in_vertex and words[2].isdigit():
                vertices = int(words[2])
        elif in_vertex and words[:1] == ["property"]:
            if len(words) != 3 or words[1] not in _PLY_SIZES:
                return None
            record += _PLY_SIZES[words[1]]
            names.append(words[2])
    if vertices is None or not formats:
        return None
    if formats[0] == "ascii":
        with open(path, "rb") as file:
            file.seek(header_bytes)
            data = file.read()
        values = data.split()
        if len(values) < vertices * len(names):
            raise ValueError(f"{path} is cut short: its header lists {vertices} points of {len(names)} values "
                             f"but the file holds {len(values)} values")
        if elements == 1 and {"x", "y", "z"} <= set(names):
            vertex_values = values[:vertices * len(names)]
            xyz = _ascii_xyz(path, vertex_values, names)
            _refuse_nonfinite(path, xyz)
            _refuse_what_open3d_cannot_read(path, data, vertex_values, names)
            return xyz
        return None
    needed = header_bytes + vertices * record
    if path.stat().st_size < needed:
        raise ValueError(f"{path} is cut short: its header lists {vertices} points ({needed} bytes) but the file "
                         f"has {path.stat().st_size} bytes")
    return None


def _ascii_xyz(path: Path, values: list[bytes], names: list[str]) -> np.ndarray:
    try:
        table = np.array(values, dtype=np.float64).reshape(-1, len(names))
    except ValueError:
        word = next(v for v in values if not _is_number(v))
        raise ValueError(f"{path}: {word.decode('ascii', 'replace')!r} is not a number; "
                         f"the file is not a readable ASCII PLY") from None
    return table[:, [names.index(axis) for axis in "xyz"]]


def _is_number(value: bytes) -> bool:
    try:
        float(value)
        return True
    except ValueError:
        return False


def _refuse_what_open3d_cannot_read(path: Path, data: bytes, values: list[bytes], names: list[str]) -> None:
    """ValueError naming the first value that Python reads but Open3D's PLY reader stops at ("inf" in
    any column, "1_0"). Open3D leaves the points after it unread, holding whatever memory held: after an
    earlier read of a like file, the right values, so comparing clouds (``_agree_with_open3d``) alone
    can miss the stop."""
    if not re.search(rb"(?i)_|inf", data):
        return
    index = next((i for i, value in enumerate(values) if b"_" in value or b"inf" in value.lower()), None)
    if index is not None:
        raise ValueError(f"{path}: Open3D cannot read point {index // len(names)}'s {names[index % len(names)]} "
                         f"value {values[index].decode('ascii', 'replace')!r} and stops there; the file is not a "
                         "readable ASCII PLY")


def _agree_with_open3d(path: Path, points: np.ndarray, xyz: np.ndarray) -> None:
    """ValueError where Open3D read an ASCII PLY's points differently from ``_ascii_xyz``: it stops at a
    value it cannot parse and leaves the rest of the cloud unread."""
    differs = np.flatnonzero(~np.isclose(points, xyz, rtol=1e-5, atol=1e-9).all(1)) if len(points) == len(xyz) \
        else np.array([min(len(points), len(xyz))])
    if len(differs):
        raise ValueError(f"{path}: a value at or before point {differs[0]} cannot be read (Open3D stops there); "
                         "the file is not a readable ASCII PLY")


def _refuse_nonfinite(path: Path, rows: np.ndarray) -> None:
    bad = np.count_nonzero(~np.isfinite(rows).all(1))
    if bad:
        raise ValueError(f"{path}: {bad} of {len(rows)} points are NaN or infinite; "
                         "remove them (invalid depth) and try again")
