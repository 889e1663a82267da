"""Camera rigs for synthetic scenes: a ring of cameras around and above the object's trajectory,
and the check that every frame stays in view.

World up is +y, the ground is ``y = 0``. Camera ``i`` of ``n`` sits at azimuth
``offset + 360 i / n`` degrees (measured from +z toward +x) and elevation
``elevations[i % len(elevations)]`` above the horizontal plane through the target, at
``distance`` metres from the target, and looks at it (OpenCV convention, image up = world up).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from toolkit.cameras import Cameras
from toolkit.synthetic.errors import FramingError, SpecError

__all__ = ["bounding_sphere", "orbit_cameras", "check_in_view"]


def bounding_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (bounding-box centre) and radius of a sphere holding all ``points`` (..., 3)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centre = (p.min(0) + p.max(0)) / 2.0
    return centre, float(np.linalg.norm(p - centre, axis=1).max())


def orbit_cameras(
    centre: Sequence[float],
    radius: float,
    n_cameras: int,
    *,
    width: int,
    height: int,
    elevations_deg: Sequence[float] = (15.0, 35.0),
    azimuth_offset_deg: float = 0.0,
    fov_y_deg: float | None = 40.0,
    distance: float | None = None,
    margin: float = 1.15,
    ground_height: float = 0.0,
) -> tuple[Cameras, float, float]:
    """A ring of cameras looking at ``centre`` that frames a sphere of ``radius`` (metres).

    Give the field of view, the distance, or both: a missing one is chosen so that the sphere,
    enlarged by ``margin``, fits inside the smaller of the two image fields of view.

    Returns:
        ``(cameras, distance, fov_y_deg)``.

    Raises:
        SpecError: impossible framing (camera inside the sphere, field of view too wide) or a
            camera at or below the ground.
    """
    if n_cameras < 1:
        raise SpecError(f"n_cameras must be >= 1, got {n_cameras}")
    aspect = width / height
    need = radius * margin

    def half_min_fov(fov_y: float) -> float:
        half_y = math.radians(fov_y) / 2
        half_x = math.atan(math.tan(half_y) * aspect)
        return min(half_y, half_x)

    if fov_y_deg is None and distance is None:
        fov_y_deg = 40.0
    if distance is None:
        distance = need / math.sin(half_min_fov(fov_y_deg))
    elif fov_y_deg is None:
        if need >= distance:
            raise SpecError(
                f"camera_distance {distance:g} m is inside the trajectory's bounding sphere (radius {radius:.3g} m, "
                f"x{margin} margin); increase camera_distance"
            )
        half = math.asin(need / distance)
        # the smaller fov must cover the sphere: convert to the vertical fov
        half_y = half if aspect >= 1 else math.atan(math.tan(half) / aspect)
        fov_y_deg = math.degrees(2 * half_y)
        if fov_y_deg >= 150:
            raise SpecError(
                f"framing the trajectory from {distance:g} m needs a {fov_y_deg:.0f} deg field of view; "
                "increase camera_distance"
            )
    elevations = list(elevations_deg) or [20.0]
    eyes = []
    for i in range(n_cameras):
        az = math.radians(azimuth_offset_deg + 360.0 * i / n_cameras)
        el = math.radians(elevations[i % len(elevations)])
        direction = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        eyes.append(np.asarray(centre, np.float64) + distance * direction)
    eyes = np.stack(eyes)
    low = int(np.argmin(eyes[:, 1]))
    if eyes[low, 1] <= ground_height + 0.02:
        raise SpecError(
            f"camera {low} would sit at y = {eyes[low, 1]:.3f} m, at or below the ground (y = {ground_height:g}); "
            "raise the camera elevations"
        )
    cams = Cameras.look_at(
        eye=torch.as_tensor(eyes), target=torch.as_tensor(np.asarray(centre, np.float64)), up=(0.0, 1.0, 0.0),
        fov_y_deg=float(fov_y_deg), width=width, height=height,
    )
    return cams, float(distance), float(fov_y_deg)


def check_in_view(cameras: Cameras, frames: np.ndarray, margin_px: float = 0.0) -> None:
    """Raise :class:`FramingError` if any point of any frame falls outside any camera's image.

    Args:
        cameras: B cameras.
        frames: (T, M, 3) points per frame (e.g. the surface vertices), metres.
        margin_px: required distance from the image border, pixels.
    """
    pts = torch.as_tensor(np.asarray(frames, dtype=np.float64))
    for c in range(len(cameras)):
        cam = cameras[c]
        for t in range(pts.shape[0]):
            pix, depth = cam.project(pts[t])
            pix, depth = pix[0].numpy(), depth[0].numpy()
            bad = (
                (depth <= cam.near)
                | (pix[:, 0] < margin_px)
                | (pix[:, 1] < margin_px)
                | (pix[:, 0] > cam.width - margin_px)
                | (pix[:, 1] > cam.height - margin_px)
            )
            if bad.any():
                i = int(np.nonzero(bad)[0][0])
                raise FramingError(
                    f"the object leaves the image of camera {c} at frame {t}: point {np.round(pts[t, i].numpy(), 3).tolist()} "
                    f"projects to pixel {np.round(pix[i], 1).tolist()} (image {cam.width}x{cam.height}, depth {depth[i]:.3f} m); "
                    "increase camera_distance or fov_y_deg (or leave one of them unset to frame automatically), "
                    "or shorten the throw"
                )
