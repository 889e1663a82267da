"""Exports of the 4D Gaussians: per-frame centres, renders, and a 3DGS PLY of the Gaussians.

PLY layout (the one the 3DGS reference code writes and common splat viewers read; binary little
endian, one ``vertex`` element, every property ``float``)::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 ... f_rest_{3(K-1)-1} opacity
    scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

* ``x y z``: centre, metres; ``nx ny nz``: zeros.
* ``f_dc_*``: degree-0 SH coefficient per channel (RGB = 0.28209479 f_dc + 0.5).
* ``f_rest_*``: higher SH bands, *channel-major* (all R coefficients, then G, then B), as 3DGS
  stores ``features_rest.transpose(1, 2).flatten(1)``.
* ``opacity``: logit (pre-sigmoid); ``scale_*``: natural log of the standard deviations (an
  isotropic Gaussian writes its one scale three times); ``rot_*``: quaternion (w, x, y, z).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from renderers.base import Gaussians, RenderOutput
from toolkit.cameras import Cameras

__all__ = [
    "ply_property_names",
    "save_ply",
    "load_ply",
    "gaussian_centers",
    "render_views",
]


def ply_property_names(sh_degree: int) -> list[str]:
    """The vertex properties of a 3DGS PLY with SH degree ``sh_degree``, in file order."""
    k = (int(sh_degree) + 1) ** 2
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def _to_gaussians(obj, time: Optional[float]) -> Gaussians:
    from toolkit.scene.gaussian_model import GaussianModel

    if isinstance(obj, Gaussians):
        return obj
    if isinstance(obj, GaussianModel):
        return obj.gaussians()
    if hasattr(obj, "gaussians_at"):
        return obj.gaussians_at(time)
    raise TypeError(f"cannot export {type(obj).__name__}: expected Gaussians, GaussianModel or a module with gaussians_at")


@torch.no_grad()
def save_ply(path: str | Path, gaussians, *, time: Optional[float] = None, min_sh_degree: int = 3) -> Path:
    """Write Gaussians as a standard 3DGS PLY (module docstring).

    Args:
        path: Output file.
        gaussians: :class:`renderers.base.Gaussians` (with ``sh`` or ``colors``), a
            :class:`GaussianModel`, or a :class:`Gaussians4DModule` (canonical Gaussians, or at
            ``time`` seconds when given).
        time: Deform the Gaussians of a 4D module to this time first.
        min_sh_degree: Pad the SH coefficients with zeros up to this degree (3 by default: the
            reference 3DGS files always carry 45 ``f_rest`` values and some viewers expect them;
            zero coefficients do not change the colour).

    Returns:
        The path written.
    """
    g = _to_gaussians(gaussians, time)
    n = len(g)
    means = g.means.detach().float().cpu().numpy()
    if g.sh is not None:
        sh = g.sh.detach().float().cpu()
    else:
        from toolkit.scene.gaussian_model import rgb_to_sh_dc

        sh = rgb_to_sh_dc(g.colors.detach().float().cpu())[:, None, :]
    k_pad = (max(0, min(int(min_sh_degree), 3)) + 1) ** 2
    if sh.shape[1] < k_pad:
        sh = torch.cat([sh, torch.zeros(n, k_pad - sh.shape[1], 3)], dim=1)
    k = sh.shape[1]
    degree = {1: 0, 4: 1, 9: 2, 16: 3}[k]
    f_dc = sh[:, 0, :].numpy()
    f_rest = sh[:, 1:, :].transpose(1, 2).reshape(n, -1).numpy()  # channel-major
    log_scales = g.log_scales.detach().float().cpu()
    if log_scales.shape[1] == 1:
        log_scales = log_scales.expand(n, 3)
    cols = [
        means,
        np.zeros((n, 3), np.float32),
        f_dc,
        f_rest,
        g.opacity_logits.detach().float().cpu().numpy()[:, None],
        log_scales.numpy(),
        g.quats.detach().float().cpu().numpy(),
    ]
    table = np.concatenate([c.reshape(n, -1).astype(np.float32) for c in cols], axis=1)
    names = ply_property_names(degree)
    assert table.shape[1] == len(names)
    header = "ply\nformat binary_little_endian 1.0\n"
    header += "comment projo4d 3D Gaussians (3DGS layout)\n"
    header += f"element vertex {n}\n" + "".join(f"property float {p}\n" for p in names) + "end_header\n"
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode("ascii") + table.astype("<f4").tobytes())
    return path


def load_ply(path: str | Path, device: torch.device | str = "cpu") -> Gaussians:
    """Read a 3DGS PLY (module docstring) into :class:`renderers.base.Gaussians` (with ``sh``).

    Accepts any SH degree; properties may be ``float`` or ``double``; extra properties are ignored.
    """
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path} is not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    fmt, n, props = None, None, []
    in_vertex = False
    for line in header:
        w = line.split()
        if not w:
            continue
        if w[0] == "format":
            fmt = w[1]
        elif w[0] == "element":
            in_vertex = w[1] == "vertex"
            if in_vertex:
                n = int(w[2])
        elif w[0] == "property" and in_vertex:
            if w[1] not in ("float", "float32", "double", "float64"):
                raise ValueError(f"{path}: unsupported property type {w[1]!r} for {w[-1]}")
            props.append((w[2], "<f4" if w[1] in ("float", "float32") else "<f8"))
    if fmt != "binary_little_endian" or n is None:
        raise ValueError(f"{path}: expected a binary_little_endian PLY with a vertex element")
    table = np.frombuffer(data, dtype=np.dtype(props), count=n, offset=end + len(b"end_header\n"))
    names = [p for p, _ in props]
    missing = {"x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0"} - set(names)
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing {sorted(missing)}")

    def col(*keys: str) -> np.ndarray:
        return np.stack([np.asarray(table[k], dtype=np.float32) for k in keys], axis=1)

    rest = sorted((p for p in names if p.startswith("f_rest_")), key=lambda p: int(p.split("_")[-1]))
    k = 1 + len(rest) // 3
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0, :] = col("f_dc_0", "f_dc_1", "f_dc_2")
    if rest:
        sh[:, 1:, :] = col(*rest).reshape(n, 3, k - 1).transpose(0, 2, 1)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(device)  # noqa: E731
    return Gaussians(
        means=t(col("x", "y", "z")),
        log_scales=t(col("scale_0", "scale_1", "scale_2")),
        quats=t(col("rot_0", "rot_1", "rot_2", "rot_3")),
        opacity_logits=t(np.asarray(table["opacity"], dtype=np.float32)),
        sh=t(sh),
    )


@torch.no_grad()
def gaussian_centers(model, times: Sequence[float] | torch.Tensor, *, min_opacity: float = 0.0) -> list[torch.Tensor]:
    """Per-frame Gaussian centres ``x̂_t = x̂_0 + Δ(x̂_0, t)`` of a 4D module.

    Args:
        model: A :class:`Gaussians4DModule` (anything with ``centers_at`` and ``gaussians``).
        times: Frame times, seconds.
        min_opacity: Keep only Gaussians with at least this opacity.

    Returns:
        One (N', 3) float32 CPU tensor per time.
    """
    centres = model.centers_at(times)
    keep = model.gaussians.opacity >= min_opacity
    return [c[keep].float().cpu() for c in centres]


@torch.no_grad()
def render_views(model, cameras: Cameras, times: Sequence[float] | torch.Tensor) -> RenderOutput:
    """Render every camera at every time; one renderer call per time.

    Returns:
        :class:`RenderOutput` with rgb (T, B, H, W, 3), alpha and depth (T, B, H, W), on the CPU.
    """
    outs = [model.render(cameras, float(t)) for t in torch.as_tensor(times).reshape(-1)]
    return RenderOutput(
        rgb=torch.stack([o.rgb for o in outs]).cpu(),
        alpha=torch.stack([o.alpha for o in outs]).cpu(),
        depth=torch.stack([o.depth for o in outs]).cpu(),
    )
