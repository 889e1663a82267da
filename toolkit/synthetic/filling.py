"""Filling a closed mesh with simulation particles on a regular lattice.

Candidates come from trimesh's voxelization, ``mesh.voxelized(pitch).fill()`` (fast and
deterministic, DESIGN section 10): every voxel the surface touches plus the enclosed ones. Kept
as is (``carve=False``) that set overestimates the volume by about half a voxel layer over the
whole surface (measured: +10 % for a 0.1 m sphere at pitch 0.005 m, +44 % at 0.02 m). By default
the candidates are therefore *carved*: only voxel centres inside the mesh (generalized winding
number > 1/2, computed with ``wp.mesh_query_point_sign_winding_number``) are kept, so
``count x pitch^3`` is an unbiased estimate of the mesh volume.

The lattice is offset by half a pitch from the world origin (centres at ``(k + 1/2) pitch``), so
faces of boxes whose corners are multiples of the pitch never pass through particle centres.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh
import warp as wp

__all__ = ["fill_mesh", "inside_mesh"]


@wp.kernel
def _winding_inside(
    mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_dist: float, inside: wp.array(dtype=wp.int32)
):
    i = wp.tid()
    q = wp.mesh_query_point_sign_winding_number(mesh, points[i], max_dist, 2.0, 0.5)
    inside[i] = wp.where(q.result and q.sign < 0.0, 1, 0)


def inside_mesh(mesh: trimesh.Trimesh, points: np.ndarray, device: str = "cpu") -> np.ndarray:
    """(N,) bool: whether each point is inside the closed mesh (generalized winding number > 1/2).

    Args:
        mesh: a closed triangle mesh (metres).
        points: (N, 3) query points (metres).
        device: Warp device.
    """
    pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0, dtype=bool)
    wmesh = wp.Mesh(
        points=wp.array(np.asarray(mesh.vertices, np.float32), dtype=wp.vec3, device=device),
        indices=wp.array(np.asarray(mesh.faces, np.int32).reshape(-1), dtype=wp.int32, device=device),
        support_winding_number=True,
    )
    out = wp.zeros(len(pts), dtype=wp.int32, device=device)
    max_dist = float(2.0 * np.linalg.norm(mesh.extents) + 1.0)
    wp.launch(
        _winding_inside, dim=len(pts), inputs=[wmesh.id, wp.array(pts, dtype=wp.vec3, device=device), max_dist, out],
        device=device,
    )
    return out.numpy().astype(bool)


def fill_mesh(mesh: trimesh.Trimesh, spacing: float, *, carve: bool = True, device: str = "cpu") -> tuple[np.ndarray, float]:
    """Particles filling a closed mesh on a regular lattice.

    Args:
        mesh: closed triangle mesh in world coordinates (metres).
        spacing: lattice pitch (metres); each particle stands for a cube of ``spacing^3``.
        carve: keep only voxel centres inside the mesh (unbiased volume); ``False`` keeps every
            voxel of ``voxelized(spacing).fill()`` (surface voxels included).
        device: Warp device for the inside test.

    Returns:
        ``(points, particle_volume)``: (N, 3) float64 particle positions sorted lexicographically
        by (x, y, z) lattice index (deterministic), and the volume per particle ``spacing^3`` (m^3).

    Raises:
        ValueError: non-positive spacing, or a mesh too thin to hold a single particle.
    """
    if not (math.isfinite(spacing) and spacing > 0):
        raise ValueError(f"particle spacing must be a positive length in metres, got {spacing!r}")
    shift = np.full(3, 0.5 * spacing)
    shifted = mesh.copy()
    shifted.apply_translation(-shift)
    vox = shifted.voxelized(spacing).fill()
    idx = np.round(np.asarray(vox.points) / spacing).astype(np.int64)
    idx = np.unique(idx, axis=0)  # sorted lexicographically
    points = idx * spacing + shift
    if carve and len(points):
        points = points[inside_mesh(mesh, points, device)]
    if len(points) == 0:
        raise ValueError(
            f"no particle fits in the mesh at spacing {spacing:g} m (mesh extents {np.round(mesh.extents, 4).tolist()} m); "
            "use a smaller spacing or a bigger object"
        )
    return points, spacing**3
