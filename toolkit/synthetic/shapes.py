"""Closed triangle meshes for synthetic objects: primitives, box composites, or a user's mesh file.

Every builder returns a watertight :class:`trimesh.Trimesh` with outward normals, centred on the
origin (the centre of its axis-aligned bounding box), sizes in metres. World up is +y, so "lying
flat" means a thin y extent. The registry :data:`SHAPES` maps a name to a :class:`ShapeBuilder`
holding the builder, its size parameters with defaults, and the bounding-box extents the
sizes imply::

    mesh = build_shape("torus", major_radius=0.12)
    SHAPES["torus"].extents(major_radius=0.12, minor_radius=0.04)   # (0.32, 0.08, 0.32)

Composite shapes (``cross``, ``letter_l``, ``letter_t``) are unions of axis-aligned boxes on a
rectilinear grid, built face by face (no boolean engine needed), so they are exactly closed.
``banana`` is a capsule bent along a circular arc; the bend preserves volume. ``apple``,
``chess``, ``cream`` and ``paste`` stand in for the Spring-Gaus objects
(:mod:`toolkit.synthetic.revolved_shapes`).
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import trimesh

from toolkit.synthetic import revolved_shapes as revolved
from toolkit.synthetic.errors import MeshFileError, SpecError

__all__ = ["ShapeBuilder", "SHAPES", "get_shape", "build_shape", "load_mesh_file", "box_union_mesh", "check_mesh"]


@dataclass(frozen=True)
class ShapeBuilder:
    """One registered shape.

    Attributes:
        name: registry key.
        build: ``(**sizes) -> Trimesh`` (sizes complete, validated).
        defaults: size parameter -> default value, metres (degrees for angles, named ``*_deg``).
        extents: ``(**sizes) -> (3,)`` bounding-box extents (x, y, z) the sizes imply, metres.
        description: one line for ``--help`` and docs.
        check: optional ``(sizes) -> None`` raising :class:`SpecError` for inconsistent sizes.
    """

    name: str
    build: Callable[..., trimesh.Trimesh]
    defaults: Mapping[str, float]
    extents: Callable[..., np.ndarray]
    description: str = ""
    check: Callable[[dict], None] | None = field(default=None)

    def complete(self, sizes: Mapping[str, float] | None) -> dict[str, float]:
        """``sizes`` with defaults filled in, validated (unknown keys, non-positive values)."""
        sizes = dict(sizes or {})
        unknown = set(sizes) - set(self.defaults)
        if unknown:
            raise SpecError(
                f"shape {self.name!r} has no size parameter(s) {sorted(unknown)}; its sizes are "
                f"{', '.join(f'{k} (default {v:g})' for k, v in self.defaults.items())}"
            )
        full = {k: float(sizes.get(k, v)) for k, v in self.defaults.items()}
        for k, v in full.items():
            if not math.isfinite(v) or v <= 0:
                unit = "degrees" if k.endswith("_deg") else "metres"
                raise SpecError(f"shape {self.name!r}: size {k} must be a positive number of {unit}, got {v!r}")
        if self.check is not None:
            self.check(full)
        return full

    def __call__(self, **sizes: float) -> trimesh.Trimesh:
        full = self.complete(sizes)
        mesh = self.build(**full)
        return _centred(mesh)


def _centred(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    lo, hi = mesh.bounds
    mesh = mesh.copy()
    mesh.apply_translation(-(lo + hi) / 2.0)
    return mesh


# ---------------------------------------------------------------------------------- primitives


def _sphere(radius: float) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=4, radius=radius)


def _box(size_x: float, size_y: float, size_z: float) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(size_x, size_y, size_z))


def _torus(major_radius: float, minor_radius: float) -> trimesh.Trimesh:
    mesh = trimesh.creation.torus(major_radius, minor_radius, major_sections=64, minor_sections=32)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (1, 0, 0)))  # axis z -> y: lies flat
    return mesh


def _check_torus(s: dict) -> None:
    if s["minor_radius"] >= s["major_radius"]:
        raise SpecError(
            f"shape 'torus': minor_radius ({s['minor_radius']:g} m) must be smaller than major_radius ({s['major_radius']:g} m)"
        )


def _capsule_z(radius: float, length: float, sections: int = 32) -> trimesh.Trimesh:
    """Capsule along z, total length ``length`` (caps included)."""
    return trimesh.creation.capsule(height=length - 2 * radius, radius=radius, count=[sections, sections])


def _capsule(radius: float, length: float) -> trimesh.Trimesh:
    mesh = _capsule_z(radius, length)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (0, 1, 0)))  # axis z -> x
    return mesh


def _check_capsule(s: dict) -> None:
    if s["length"] <= 2 * s["radius"]:
        raise SpecError(f"shape 'capsule': length ({s['length']:g} m) must exceed 2 x radius ({2 * s['radius']:g} m)")


def _bend(v: np.ndarray, bend_radius: float) -> np.ndarray:
    """Bend points of a body along z (arc parameter = z) toward +y about the centre (0, R, 0),
    then rotate the arc into the xy plane. Volume-preserving for cross-sections symmetric in y."""
    phi = v[:, 2] / bend_radius
    r = bend_radius - v[:, 1]
    bent = np.stack([v[:, 0], bend_radius - r * np.cos(phi), r * np.sin(phi)], axis=1)
    return np.stack([bent[:, 2], bent[:, 1], -bent[:, 0]], axis=1)  # rotation about y: x <- z, z <- -x


def _banana(radius: float, length: float, bend_deg: float) -> trimesh.Trimesh:
    """A capsule of total length ``length`` along its centreline, bent by ``bend_deg`` in the xy plane."""
    mesh = _capsule_z(radius, length, sections=32)
    verts, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=length / 16)
    mesh = trimesh.Trimesh(_bend(np.asarray(verts), length / math.radians(bend_deg)), faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _banana_extents(radius: float, length: float, bend_deg: float) -> np.ndarray:
    """Extents of the analytic bent capsule surface, sampled densely."""
    a = np.linspace(0, 2 * np.pi, 721)
    half = length / 2 - radius
    z = np.linspace(-half, half, 401)
    A, Z = np.meshgrid(a, z)
    tube = np.stack([radius * np.cos(A), radius * np.sin(A), Z], -1).reshape(-1, 3)
    u = np.linspace(0, np.pi / 2, 181)
    U, B = np.meshgrid(u, a)
    cap = np.stack([radius * np.cos(U) * np.cos(B), radius * np.cos(U) * np.sin(B), radius * np.sin(U)], -1).reshape(-1, 3)
    pts = np.concatenate([tube, cap + [0, 0, half], cap * [1, 1, -1] - [0, 0, half]])
    bent = _bend(pts, length / math.radians(bend_deg))
    return bent.max(0) - bent.min(0)


def _check_banana(s: dict) -> None:
    if s["length"] <= 2 * s["radius"]:
        raise SpecError(f"shape 'banana': length ({s['length']:g} m) must exceed 2 x radius ({2 * s['radius']:g} m)")
    if not 0 < s["bend_deg"] < 300:
        raise SpecError(f"shape 'banana': bend_deg must be in (0, 300) degrees, got {s['bend_deg']:g}")
    if s["length"] / math.radians(s["bend_deg"]) <= s["radius"] * 1.5:
        raise SpecError(
            f"shape 'banana': bend too tight for its thickness (centreline radius {s['length'] / math.radians(s['bend_deg']):.3g} m "
            f"<= 1.5 x radius {s['radius']:g} m); reduce bend_deg or radius, or increase length"
        )


# ---------------------------------------------------------------------------------- box unions


def box_union_mesh(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray, occupied: np.ndarray) -> trimesh.Trimesh:
    """Closed surface of a union of cells of a rectilinear grid.

    Args:
        xs, ys, zs: increasing cell edge coordinates along each axis (metres), lengths nx+1, ny+1, nz+1.
        occupied: (nx, ny, nz) bool, which cells are solid. Cells touching only along an edge or a
            corner give a non-manifold surface; the built-in shapes never do that.

    Returns:
        A watertight mesh (two triangles per boundary cell face, outward winding).
    """
    occ = np.asarray(occupied, dtype=bool)
    padded = np.pad(occ, 1)
    verts: dict[tuple[int, int, int], int] = {}
    faces: list[tuple[int, int, int]] = []

    def vid(i: int, j: int, k: int) -> int:
        key = (i, j, k)
        if key not in verts:
            verts[key] = len(verts)
        return verts[key]

    for axis in range(3):
        step = [0, 0, 0]
        step[axis] = 1
        for i, j, k in zip(*np.nonzero(occ)):
            for direction in (-1, 1):
                ni, nj, nk = i + 1 + direction * step[0], j + 1 + direction * step[1], k + 1 + direction * step[2]
                if padded[ni, nj, nk]:
                    continue
                # the face lies at cell index c (+1 for the positive side) along `axis`
                corner = [i, j, k]
                corner[axis] += 1 if direction > 0 else 0
                a1, a2 = [(axis + 1) % 3, (axis + 2) % 3]
                quad = []
                for d1, d2 in ((0, 0), (1, 0), (1, 1), (0, 1)):
                    c = list(corner)
                    c[a1] += d1
                    c[a2] += d2
                    quad.append(vid(*c))
                # (a1, a2, axis) is right-handed: counter-clockwise in (a1, a2) faces +axis
                if direction < 0:
                    quad = quad[::-1]
                faces.append((quad[0], quad[1], quad[2]))
                faces.append((quad[0], quad[2], quad[3]))
    grid = np.array(sorted(verts, key=verts.get), dtype=np.int64)
    points = np.stack([np.asarray(xs)[grid[:, 0]], np.asarray(ys)[grid[:, 1]], np.asarray(zs)[grid[:, 2]]], axis=1)
    return trimesh.Trimesh(points.astype(np.float64), np.array(faces, dtype=np.int64), process=True)


def _cross(span: float, arm_width: float, thickness: float) -> trimesh.Trimesh:
    """An upright plus sign in the xy plane, extruded along z."""
    a = (span - arm_width) / 2
    edges = np.array([0.0, a, a + arm_width, span])
    occ = np.zeros((3, 3, 1), bool)
    occ[1, :, 0] = True
    occ[:, 1, 0] = True
    return box_union_mesh(edges, edges, np.array([0.0, thickness]), occ)


def _check_cross(s: dict) -> None:
    if s["arm_width"] >= s["span"]:
        raise SpecError(f"shape 'cross': arm_width ({s['arm_width']:g} m) must be smaller than span ({s['span']:g} m)")


def _letter_l(height: float, width: float, stroke: float, thickness: float) -> trimesh.Trimesh:
    """An upright "L" in the xy plane (stem on the left, foot at the bottom), extruded along z."""
    occ = np.zeros((2, 2, 1), bool)
    occ[0, :, 0] = True  # stem
    occ[1, 0, 0] = True  # foot
    return box_union_mesh(np.array([0.0, stroke, width]), np.array([0.0, stroke, height]), np.array([0.0, thickness]), occ)


def _letter_t(height: float, width: float, stroke: float, thickness: float) -> trimesh.Trimesh:
    """An upright "T" in the xy plane (bar at the top, centred stem), extruded along z."""
    a = (width - stroke) / 2
    occ = np.zeros((3, 2, 1), bool)
    occ[:, 1, 0] = True  # bar
    occ[1, 0, 0] = True  # stem
    return box_union_mesh(
        np.array([0.0, a, a + stroke, width]), np.array([0.0, height - stroke, height]), np.array([0.0, thickness]), occ
    )


def _check_letter(name: str) -> Callable[[dict], None]:
    def check(s: dict) -> None:
        if s["stroke"] >= min(s["height"], s["width"]):
            raise SpecError(
                f"shape {name!r}: stroke ({s['stroke']:g} m) must be smaller than height and width "
                f"({s['height']:g} m, {s['width']:g} m)"
            )

    return check


def _torus_extents(major_radius: float, minor_radius: float) -> np.ndarray:
    outer = 2 * (major_radius + minor_radius)
    return np.array([outer, 2 * minor_radius, outer])


def _plate_extents(width: float, height: float, thickness: float) -> np.ndarray:
    return np.array([width, height, thickness])


SHAPES: dict[str, ShapeBuilder] = {
    b.name: b
    for b in (
        ShapeBuilder("sphere", _sphere, {"radius": 0.1}, lambda radius: np.full(3, 2 * radius), "icosphere (4 subdivisions)"),
        ShapeBuilder(
            "box", _box, {"size_x": 0.2, "size_y": 0.12, "size_z": 0.16},
            lambda size_x, size_y, size_z: np.array([size_x, size_y, size_z]), "axis-aligned box",
        ),
        ShapeBuilder(
            "torus", _torus, {"major_radius": 0.1, "minor_radius": 0.04}, _torus_extents,
            "torus lying flat (axis +y)", _check_torus,
        ),
        ShapeBuilder(
            "capsule", _capsule, {"radius": 0.05, "length": 0.24},
            lambda radius, length: np.array([length, 2 * radius, 2 * radius]),
            "capsule along x (length includes the caps)", _check_capsule,
        ),
        ShapeBuilder(
            "cross", _cross, {"span": 0.24, "arm_width": 0.07, "thickness": 0.07},
            lambda span, arm_width, thickness: _plate_extents(span, span, thickness),
            "upright plus sign (xy plane) extruded along z", _check_cross,
        ),
        ShapeBuilder(
            "letter_l", _letter_l, {"height": 0.24, "width": 0.16, "stroke": 0.06, "thickness": 0.06},
            lambda height, width, stroke, thickness: _plate_extents(width, height, thickness),
            "upright letter L extruded along z", _check_letter("letter_l"),
        ),
        ShapeBuilder(
            "letter_t", _letter_t, {"height": 0.24, "width": 0.2, "stroke": 0.06, "thickness": 0.06},
            lambda height, width, stroke, thickness: _plate_extents(width, height, thickness),
            "upright letter T extruded along z", _check_letter("letter_t"),
        ),
        ShapeBuilder(
            "banana", _banana, {"radius": 0.04, "length": 0.3, "bend_deg": 90.0}, _banana_extents,
            "capsule bent along a circular arc in the xy plane (length along the centreline)", _check_banana,
        ),
        # stand-ins for the other Spring-Gaus objects (toolkit.synthetic.revolved_shapes)
        ShapeBuilder("apple", revolved.apple, {"radius": 0.09, "height": 0.16}, revolved.apple_extents,
                     "flattened sphere with a dimple at each pole (axis +y)", revolved.check_apple),
        ShapeBuilder("chess", revolved.chess, {"width": 0.12, "height": 0.2}, revolved.chess_extents,
                     "chess pawn standing on +y (base, stem, collar, ball head)", revolved.check_chess),
        ShapeBuilder("cream", revolved.cream, {"base_radius": 0.1, "height": 0.16}, revolved.cream_extents,
                     "soft-serve dollop of three tiers narrowing to a tip on +y", revolved.check_cream),
        ShapeBuilder("paste", revolved.paste, {"length": 0.26, "width": 0.08, "thickness": 0.05}, revolved.paste_extents,
                     "bead of paste: a capsule along x flattened in y", revolved.check_paste),
    )
}


def get_shape(name: str) -> ShapeBuilder:
    """The registered shape ``name``; unknown names raise :class:`SpecError` listing the choices."""
    if name in SHAPES:
        return SHAPES[name]
    close = difflib.get_close_matches(str(name), list(SHAPES), n=3)
    hint = f" (did you mean {', '.join(repr(c) for c in close)}?)" if close else ""
    raise SpecError(f"unknown shape {name!r}{hint}; known shapes: {', '.join(SHAPES)}; or give a mesh file")


def build_shape(name: str, **sizes: float) -> trimesh.Trimesh:
    """Build the registered shape ``name`` with ``sizes`` (metres), centred on the origin."""
    return get_shape(name)(**sizes)


# ---------------------------------------------------------------------------------- mesh files


def check_mesh(mesh: trimesh.Trimesh, source: str) -> trimesh.Trimesh:
    """Validate a mesh for simulation: non-empty, finite, closed; orient normals outward.

    Raises:
        MeshFileError: naming ``source`` and the problem.
    """
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise MeshFileError(f"{source}: the mesh is empty (no triangles)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshFileError(f"{source}: the mesh has NaN or infinite vertex coordinates")
    mesh = mesh.copy()
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)
    if not mesh.is_watertight:
        open_edges = int(len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)))
        raise MeshFileError(
            f"{source}: the mesh is not closed ({open_edges} boundary edges after merging vertices and filling small "
            "holes); the generator needs a watertight surface to fill with particles"
        )
    trimesh.repair.fix_normals(mesh)
    if mesh.volume <= 0:
        raise MeshFileError(f"{source}: the mesh encloses no volume ({mesh.volume:g} m^3)")
    return mesh


def load_mesh_file(path: str | Path, scale: float = 1.0) -> trimesh.Trimesh:
    """Load a closed mesh from a file trimesh reads (OBJ, PLY, STL, OFF, GLB, ...), scale it by
    ``scale`` (file units -> metres) and centre it on the origin.

    Raises:
        MeshFileError: missing or unreadable file, empty, non-finite or open mesh (naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise MeshFileError(f"mesh file {path} does not exist")
    if not (math.isfinite(scale) and scale > 0):
        raise MeshFileError(f"{path}: mesh scale must be a positive number, got {scale!r}")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise MeshFileError(f"cannot read mesh file {path}: {type(exc).__name__}: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshFileError(f"{path}: no triangle mesh found in the file (got {type(mesh).__name__})")
    mesh = check_mesh(mesh, str(path))
    mesh.apply_scale(scale)
    return _centred(mesh)
