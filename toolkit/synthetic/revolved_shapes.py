"""Shapes in the spirit of the Spring-Gaus synthetic objects: apple, chess pawn, cream, paste.

Spring-Gaus (Zhong et al., ECCV 2024) evaluates on seven elastic objects: apple, banana, chess,
cream, cross, paste and torus. Its meshes are not part of this repository; ``banana``, ``cross``
and ``torus`` are built in :mod:`toolkit.synthetic.shapes`, and this module adds stand-ins for the
other four, each described by a few sizes in metres:

* ``apple``: a slightly flattened sphere with a dimple at each pole (a surface of revolution);
* ``chess``: a pawn (a base, a tapering stem, a collar and a ball head; a surface of revolution);
* ``cream``: a dollop of soft-serve cream, three tiers narrowing to a tip (a surface of revolution);
* ``paste``: a bead of squeezed paste, a capsule along x flattened in y.

A surface of revolution is built from a profile ``(r, y)`` that starts and ends on the axis
(``r = 0``), revolved about +y with 64 sections, so it is closed. With the sections starting at
angle 0 the x and z extents are exactly twice the profile's largest radius.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import trimesh

from toolkit.synthetic.errors import SpecError

#: sections of a surface of revolution (a multiple of 4, so x and z extents are exact)
SECTIONS = 64


def _revolve(profile: np.ndarray) -> trimesh.Trimesh:
    """Revolve a profile ``(n, 2)`` of ``(r, y)`` points (first and last on the axis) about +y."""
    mesh = trimesh.creation.revolve(profile, sections=SECTIONS)  # about +z, the profile's y as z
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-math.pi / 2, (1, 0, 0)))  # z -> y
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _profile_extents(profile: np.ndarray) -> np.ndarray:
    r_max = float(profile[:, 0].max())
    return np.array([2 * r_max, float(np.ptp(profile[:, 1])), 2 * r_max])


def revolved(profile: Callable[..., np.ndarray]) -> tuple[Callable[..., trimesh.Trimesh], Callable[..., np.ndarray]]:
    """The builder and the extents of the surface of revolution of ``profile(**sizes)``."""
    return (lambda **sizes: _revolve(profile(**sizes))), (lambda **sizes: _profile_extents(profile(**sizes)))


# ---------------------------------------------------------------------------------- apple


def apple_profile(radius: float, height: float) -> np.ndarray:
    """Profile of the apple: an ellipse of half-width ``radius`` and half-height ``height / 2``,
    with both poles pushed in by 12 % of the radius (the stem and calyx dimples)."""
    t = np.linspace(0.0, math.pi, 65)
    dimple = 0.12 * radius
    y = -0.5 * height * np.cos(t) + dimple * np.exp(-(t / 0.35) ** 2) - dimple * np.exp(-((math.pi - t) / 0.35) ** 2)
    r = radius * np.sin(t)
    r[0] = r[-1] = 0.0
    return np.stack([r, y], axis=1)


def check_apple(s: dict) -> None:
    if not 0.5 * s["radius"] <= s["height"] <= 3.0 * s["radius"]:
        raise SpecError(f"shape 'apple': height ({s['height']:g} m) must be between 0.5 and 3 x radius ({s['radius']:g} m)")


# ---------------------------------------------------------------------------------- chess pawn


def chess_profile(width: float, height: float) -> np.ndarray:
    """Profile of a pawn of base diameter ``width`` and total height ``height``: a base, a
    tapering stem, a collar and a ball head of radius ``min(0.25 width, 0.2 height)``."""
    w, h = width, height
    body = [(0.0, 0.0), (0.5 * w, 0.0), (0.5 * w, 0.08 * h), (0.38 * w, 0.14 * h), (0.22 * w, 0.45 * h),
            (0.32 * w, 0.55 * h), (0.32 * w, 0.60 * h), (0.16 * w, 0.63 * h)]
    head_r = min(0.25 * w, 0.2 * h)
    centre = h - head_r
    t0 = -math.acos(min(1.0, 0.16 * w / head_r))
    t = np.linspace(t0, math.pi / 2, 24)
    head = np.stack([head_r * np.cos(t), centre + head_r * np.sin(t)], axis=1)
    head[-1] = (0.0, h)
    return np.concatenate([np.array(body), head])


def check_chess(s: dict) -> None:
    if not 1.2 * s["width"] <= s["height"] <= 3.0 * s["width"]:
        raise SpecError(f"shape 'chess': height ({s['height']:g} m) must be between 1.2 and 3 x width ({s['width']:g} m)")


# ---------------------------------------------------------------------------------- cream


def cream_profile(base_radius: float, height: float) -> np.ndarray:
    """Profile of a soft-serve dollop: radius ``base_radius`` at the bottom narrowing to a tip at
    ``height``, with three tiers (a ripple of 10 % of the local radius)."""
    s = np.linspace(0.0, 1.0, 73)
    r = base_radius * (1.0 - s) ** 0.7 * (1.0 + 0.1 * np.sin(2 * math.pi * 3 * s))
    r[-1] = 0.0
    profile = np.stack([r, height * s], axis=1)
    return np.concatenate([[[0.0, 0.0]], profile])


def check_cream(s: dict) -> None:
    if not 0.5 * s["base_radius"] <= s["height"] <= 4.0 * s["base_radius"]:
        raise SpecError(
            f"shape 'cream': height ({s['height']:g} m) must be between 0.5 and 4 x base_radius ({s['base_radius']:g} m)")


# ---------------------------------------------------------------------------------- paste


def paste(length: float, width: float, thickness: float) -> trimesh.Trimesh:
    """A capsule along x of total length ``length`` and diameter ``width``, flattened in y to
    ``thickness``."""
    mesh = trimesh.creation.capsule(height=length - width, radius=width / 2, count=[32, 32])
    mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (0, 1, 0)))  # axis z -> x
    mesh.apply_scale((1.0, thickness / width, 1.0))
    return mesh


def paste_extents(length: float, width: float, thickness: float) -> np.ndarray:
    return np.array([length, thickness, width])


def check_paste(s: dict) -> None:
    if s["length"] <= s["width"]:
        raise SpecError(f"shape 'paste': length ({s['length']:g} m) must exceed width ({s['width']:g} m)")
    if s["thickness"] > s["width"]:
        raise SpecError(f"shape 'paste': thickness ({s['thickness']:g} m) must not exceed width ({s['width']:g} m)")


apple, apple_extents = revolved(apple_profile)
chess, chess_extents = revolved(chess_profile)
cream, cream_extents = revolved(cream_profile)
