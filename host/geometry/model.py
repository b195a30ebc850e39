"""Workpiece models: OBJ/PLY loading to wireframes, and a built-in manipulator for the demo."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from host.geometry.transforms import ArrayLike, FloatArray, make_T, rot_x, transform_points

IntArray = npt.NDArray[np.int64]

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
MANIPULATOR_SIDES = 16  # polygon sides of each cylinder in the built-in model


@dataclass(frozen=True, eq=False)
class Wireframe:
    """Vertices (N,3) float64 in mm, edges (M,2) and optional triangles (K,3) as int64 indices."""

    vertices: FloatArray
    edges: IntArray
    faces: IntArray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))

    def __post_init__(self) -> None:
        v = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        e = np.ascontiguousarray(self.edges, dtype=np.int64).reshape(-1, 2)
        f = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)
        for name, idx in (("edge", e), ("face", f)):
            if idx.size and (idx.min() < 0 or idx.max() >= len(v)):
                raise ValueError(f"{name} index outside 0..{len(v) - 1}")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "edges", e)
        object.__setattr__(self, "faces", f)

    @classmethod
    def from_polygons(cls, vertices: ArrayLike, polygons: list[list[int]]) -> Wireframe:
        """Wireframe whose edges are the polygon outlines; faces are fan triangles."""
        tris = [(p[0], p[i], p[i + 1]) for p in polygons for i in range(1, len(p) - 1)]
        rings = [
            (p[i], p[(i + 1) % len(p)]) for p in polygons if len(p) >= 2 for i in range(len(p))
        ]
        return cls(np.asarray(vertices), unique_edges(rings), np.asarray(tris).reshape(-1, 3))

    def transformed(self, T: ArrayLike) -> Wireframe:
        """The model with vertices mapped by a 4x4 transform."""
        return Wireframe(transform_points(T, self.vertices), self.edges, self.faces)

    def merged(self, other: Wireframe) -> Wireframe:
        """Union of two models (indices of `other` shifted)."""
        n = len(self.vertices)
        return Wireframe(
            np.vstack([self.vertices, other.vertices]),
            np.vstack([self.edges, other.edges + n]),
            np.vstack([self.faces, other.faces + n]),
        )


def unique_edges(pairs: ArrayLike) -> IntArray:
    """Undirected, deduplicated edges (M,2) with the smaller index first; self-loops dropped."""
    e = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    e = np.sort(e, axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0)


def load_model(path: str | Path) -> Wireframe:
    """Load .obj or .ply by suffix."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".obj":
        return load_obj(p)
    if suffix == ".ply":
        return load_ply(p)
    raise ValueError(f"unsupported model format {suffix!r} (use .obj or .ply)")


def load_obj(path: str | Path) -> Wireframe:
    """Wavefront OBJ: v, f (v, v/vt, v//vn, v/vt/vn, negative indices) and l lines."""
    verts: list[list[float]] = []
    polys: list[list[int]] = []
    lines: list[tuple[int, int]] = []
    for lineno, raw in enumerate(Path(path).read_text().splitlines(), 1):
        parts = raw.split("#", 1)[0].split()
        if not parts:
            continue
        try:
            if parts[0] == "v":
                verts.append([float(x) for x in parts[1:4]])
            elif parts[0] in ("f", "l"):
                idx = [_obj_index(tok, len(verts)) for tok in parts[1:]]
                if parts[0] == "f":
                    polys.append(idx)
                else:
                    lines.extend(itertools.pairwise(idx))
        except (ValueError, IndexError) as exc:
            raise ValueError(f"{path}:{lineno}: bad OBJ line {raw!r}") from exc
    model = Wireframe.from_polygons(np.asarray(verts).reshape(-1, 3), polys)
    if not lines:
        return model
    edges = unique_edges(np.vstack([model.edges, np.asarray(lines).reshape(-1, 2)]))
    return Wireframe(model.vertices, edges, model.faces)


def _obj_index(token: str, n_vertices: int) -> int:
    """Zero-based vertex index of an OBJ face token; negative indices count from the end."""
    i = int(token.split("/", 1)[0])
    if i == 0:
        raise ValueError("OBJ indices start at 1")
    return i - 1 if i > 0 else n_vertices + i


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list[tuple[str, str, str | None]]  # (name, value type, list-count type or None)


def load_ply(path: str | Path) -> Wireframe:
    """PLY, ascii or binary_little_endian: vertex x/y/z, face vertex_indices, edge vertex1/2."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    body_start = data.index(b"\n", end) + 1
    fmt, elements = _ply_header(data[:end].decode("ascii").splitlines())
    if fmt == "ascii":
        values = _ply_read_ascii(data[body_start:].decode("ascii").split(), elements)
    elif fmt == "binary_little_endian":
        values = _ply_read_binary(data, body_start, elements)
    else:
        raise ValueError(f"{path}: PLY format {fmt!r} not supported")
    verts = np.stack([values["vertex"][k] for k in ("x", "y", "z")], axis=1).astype(np.float64)
    faces = values.get("face", {}).get("vertex_indices", values.get("face", {}).get("vertex_index"))
    model = Wireframe.from_polygons(verts, [list(map(int, f)) for f in (faces or [])])
    if "edge" in values:
        pairs = np.stack([values["edge"]["vertex1"], values["edge"]["vertex2"]], axis=1)
        model = Wireframe(
            model.vertices, unique_edges(np.vstack([model.edges, pairs])), model.faces
        )
    return model


def _ply_header(lines: list[str]) -> tuple[str, list[_PlyElement]]:
    """Format name and element declarations from the header lines."""
    fmt, elements = "", []
    for line in lines[1:]:
        w = line.split()
        if not w or w[0] in ("comment", "obj_info"):
            continue
        if w[0] == "format":
            fmt = w[1]
        elif w[0] == "element":
            elements.append(_PlyElement(w[1], int(w[2]), []))
        elif w[0] == "property" and w[1] == "list":
            elements[-1].props.append((w[4], PLY_TYPES[w[3]], PLY_TYPES[w[2]]))
        elif w[0] == "property":
            elements[-1].props.append((w[2], PLY_TYPES[w[1]], None))
    return fmt, elements


PlyValues = dict[str, dict[str, list]]  # type: ignore[type-arg]


def _ply_read_ascii(tokens: list[str], elements: list[_PlyElement]) -> PlyValues:
    """Walk the ascii body token by token."""
    out: PlyValues = {}
    pos = 0
    for el in elements:
        cols: dict[str, list] = {name: [] for name, _, _ in el.props}  # type: ignore[type-arg]
        for _ in range(el.count):
            for name, vtype, ltype in el.props:
                conv = float if vtype.startswith("f") else int
                if ltype is None:
                    cols[name].append(conv(tokens[pos]))
                    pos += 1
                else:
                    n = int(tokens[pos])
                    cols[name].append([conv(t) for t in tokens[pos + 1 : pos + 1 + n]])
                    pos += 1 + n
        out[el.name] = cols
    return out


def _ply_read_binary(data: bytes, pos: int, elements: list[_PlyElement]) -> PlyValues:
    """Binary little-endian body: fixed-size elements in one frombuffer, lists row by row."""
    out: PlyValues = {}
    for el in elements:
        if all(lt is None for _, _, lt in el.props):
            dt = np.dtype([(name, "<" + vt) for name, vt, _ in el.props])
            arr = np.frombuffer(data, dtype=dt, count=el.count, offset=pos)
            pos += dt.itemsize * el.count
            out[el.name] = {name: arr[name].tolist() for name, _, _ in el.props}
            continue
        cols: dict[str, list] = {name: [] for name, _, _ in el.props}  # type: ignore[type-arg]
        for _ in range(el.count):
            for name, vt, lt in el.props:
                if lt is None:
                    v = np.frombuffer(data, "<" + vt, 1, pos)
                    cols[name].append(v[0].item())
                    pos += v.itemsize
                    continue
                n = int(np.frombuffer(data, "<" + lt, 1, pos)[0])
                pos += np.dtype(lt).itemsize
                cols[name].append(np.frombuffer(data, "<" + vt, n, pos).tolist())
                pos += n * np.dtype(vt).itemsize
        out[el.name] = cols
    return out


def cylinder(radius_mm: float, height_mm: float, sides: int = MANIPULATOR_SIDES) -> Wireframe:
    """Closed cylinder along +z from z = 0, as rings, rungs and capped faces."""
    a = np.linspace(0.0, 2.0 * math.pi, sides, endpoint=False)
    ring = np.stack([radius_mm * np.cos(a), radius_mm * np.sin(a)], axis=1)
    verts = np.vstack(
        [np.hstack([ring, np.zeros((sides, 1))]), np.hstack([ring, np.full((sides, 1), height_mm)])]
    )
    i = np.arange(sides)
    j = (i + 1) % sides
    sides_q = [
        [int(a0), int(b0), int(b0) + sides, int(a0) + sides] for a0, b0 in zip(i, j, strict=True)
    ]
    caps = [list(range(sides)), list(range(2 * sides - 1, sides - 1, -1))]
    return Wireframe.from_polygons(verts, sides_q + caps)


def box(sx_mm: float, sy_mm: float, sz_mm: float) -> Wireframe:
    """Axis-aligned box centred in x, y, from z = 0 to sz."""
    x, y = 0.5 * sx_mm, 0.5 * sy_mm
    v = [[-x, -y, 0], [x, -y, 0], [x, y, 0], [-x, y, 0]]
    verts = np.array(v + [[p[0], p[1], sz_mm] for p in v], dtype=np.float64)
    quads = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    return Wireframe.from_polygons(verts, quads)


def manipulator_wireframe(sides: int = MANIPULATOR_SIDES) -> Wireframe:
    """The demo workpiece: a water-hydraulic arm standing on the floor (z up, mm)."""
    parts = [
        cylinder(300.0, 150.0, sides),  # base plate
        cylinder(120.0, 600.0, sides).transformed(make_T(np.eye(3), [0, 0, 150])),  # column
        box(300, 300, 200).transformed(make_T(np.eye(3), [0, 0, 750])),  # shoulder housing
        cylinder(70.0, 800.0, sides).transformed(make_T(rot_x(-math.pi / 3), [0, 0, 850])),  # arm
        cylinder(55.0, 650.0, sides).transformed(make_T(rot_x(-0.7 * math.pi), [0, 693, 1250])),
        box(160, 120, 120).transformed(make_T(np.eye(3), [0, 1219, 748])),  # wrist
        box(30, 40, 180).transformed(make_T(np.eye(3), [-55, 1219, 568])),  # gripper fingers
        box(30, 40, 180).transformed(make_T(np.eye(3), [55, 1219, 568])),
    ]
    model = parts[0]
    for p in parts[1:]:
        model = model.merged(p)
    return model
