"""Tile-based 3D Gaussian splatting rasterizer written with Warp kernels (registered as ``"warp"``).

The same kernels run on ``cpu`` and ``cuda``; the device is taken from the input tensors and, on
CUDA, every launch goes to torch's current stream. The renderer follows the exact, tile-independent
contribution rule of :mod:`renderers.base`, so its images match the dense ``"torch"`` reference to
float32 round-off (up to the order of Gaussians whose centres have exactly equal depth).

Pipeline (one call renders the B cameras of a frame; they share width and height):

1. ``_project`` (one thread per camera and Gaussian): 3D covariance from scales and the
   normalized quaternion, world->camera transform, near-plane cull (``z <= near``; no far plane),
   EWA Jacobian with ``x/z``, ``y/z`` clamped by the reference's rule
   (:data:`renderers.torch_reference.CLAMP_MARGIN`), 2D covariance plus the 0.3 px low-pass,
   conic, sigmoid opacity. Differentiated by Warp's autodiff (the same kernel launched with
   ``adjoint=True`` in the backward pass; its inputs are never overwritten).
2. ``_count_tiles``: the exact axis-aligned bounding box of the ellipse on which
   ``opacity * exp(-q / 2) = 1/255`` (opacity-aware; a little padded against round-off), turned into
   a rectangle of tiles (16 x 16 px on CUDA, 4 x 4 px on the CPU: :func:`tile_size`). Not
   differentiated.
3. Binning outside any differentiated region: a prefix sum of the per-Gaussian tile counts
   (torch; the total is read back to size the buffers: one host sync per call); ``_write_keys``
   writes one 64-bit key ``(camera * n_tiles + tile) << 32 | float_bits(z)`` per Gaussian-tile
   overlap (positive floats order like their bit patterns); ``wp.utils.radix_sort_pairs`` sorts
   only the bits in use (stable: equal depths keep the input order, as in the reference);
   ``_tile_ranges`` finds each tile's [start, end) in the sorted list.
4. ``_raster_fwd`` (``wp.launch_tiled``, one block per tile, one thread per pixel): the tile's list
   is walked front to back in batches of 256 that the block gathers cooperatively into shared
   memory (``tile_load`` + ``tile_load_indexed``); the block leaves early once every pixel has hit
   the transmittance cut-off. Writes rgb (background composited), alpha, depth, the final
   transmittance and the number of list entries each pixel consumed.
5. ``_raster_bwd``: back-to-front replay per pixel from the saved transmittance and count
   (``T_i = T_{i+1} / (1 - alpha_i)``), gradients for the 2D mean, conic, opacity, colour and depth
   of every contributing Gaussian, reduced over each 32-lane warp with shuffles on CUDA and
   accumulated with atomics.

On the CPU, Warp runs a tiled launch with one lane per block unless
``wp.config.enable_cpu_blocks`` is set. The raster kernels handle any block width: each lane
loops over ``tile² / block_dim`` pixels of its tile; a one-lane block walks the list directly
(no shared-memory batches, no block reductions), wider blocks take the CUDA path above (the tests
run it on the CPU with ``enable_cpu_blocks``). The warp shuffles are compiled only for CUDA; on
the CPU each lane adds its own gradients.

Memory per call: per camera-Gaussian two float4 (2D mean/depth, conic/opacity), a colour, an int4
tile rectangle and a count; per overlap a 64-bit key and a 32-bit index, twice (radix sort
scratch); per tile an int2 range; per pixel rgb, alpha, depth, transmittance and a count. Gradients
of the camera parameters are not computed.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Optional

import torch
import warp as wp

from renderers import register_renderer
from renderers.base import ALPHA_MAX, ALPHA_MIN, LOW_PASS, T_MIN, Gaussians, Renderer, RenderOutput
from renderers.torch_reference import CLAMP_MARGIN, validate_render_inputs, gaussian_colors

if TYPE_CHECKING:  # pragma: no cover
    from toolkit.cameras import Cameras

__all__ = ["BATCH", "CPU_TILE_SIZE", "TILE_SIZE", "WarpTileRenderer", "tile_size"]

TILE_SIZE = 16  # tile edge in pixels on CUDA (one pixel per lane of a 256-lane block)
CPU_TILE_SIZE = 4  # tile edge on the CPU, where a tile is one serial loop: shorter lists per pixel
BATCH = 256  # Gaussians gathered into shared memory per step; the CUDA block size
_BBOX_PAD = 1.0e-4  # relative padding of the cull box against round-off in the conic inversion

wp.set_module_options({"enable_backward": False, "block_dim": BATCH})

_ALPHA_MIN = wp.constant(ALPHA_MIN)
_ALPHA_MAX = wp.constant(ALPHA_MAX)
_T_MIN = wp.constant(T_MIN)
_LOW_PASS = wp.constant(LOW_PASS)
_CLAMP_MARGIN_C = wp.constant(CLAMP_MARGIN)
_BBOX_PAD_C = wp.constant(_BBOX_PAD)
_BATCH = wp.constant(BATCH)
_LOG255 = wp.constant(math.log(255.0))

# ---------------------------------------------------------------------------------------------
# CUDA warp-level helpers for the backward pass (native snippets, all 32 lanes of a warp must call
# them together). On the CPU a lane never shares a reduction, so they reduce to the identity.


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return __any_sync(0xffffffffu, flag) ? 1 : 0;
#else
    return flag;
#endif
"""
)
def _warp_any(flag: int) -> int: ...


# Whether this lane adds the (warp-summed) gradients to global memory: lane 0 of the warp on CUDA,
# on the CPU every lane that contributed.
@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    return (threadIdx.x & 31u) == 0u ? 1 : 0;
#else
    return contrib;
#endif
"""
)
def _warp_flush(contrib: int) -> int: ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    for (int off = 16; off > 0; off >>= 1) {
        v.c[0] += __shfl_xor_sync(0xffffffffu, v.c[0], off);
        v.c[1] += __shfl_xor_sync(0xffffffffu, v.c[1], off);
        v.c[2] += __shfl_xor_sync(0xffffffffu, v.c[2], off);
        v.c[3] += __shfl_xor_sync(0xffffffffu, v.c[3], off);
    }
#endif
    return v;
"""
)
def _warp_sum4(v: wp.vec4) -> wp.vec4: ...


@wp.func_native(
    """
#if defined(__CUDA_ARCH__)
    for (int off = 16; off > 0; off >>= 1) {
        v.c[0] += __shfl_xor_sync(0xffffffffu, v.c[0], off);
        v.c[1] += __shfl_xor_sync(0xffffffffu, v.c[1], off);
        v.c[2] += __shfl_xor_sync(0xffffffffu, v.c[2], off);
    }
#endif
    return v;
"""
)
def _warp_sum3(v: wp.vec3) -> wp.vec3: ...


# ---------------------------------------------------------------------------------------------
# Kernels


@wp.func
def _quat_to_rotmat(q: wp.vec4) -> wp.mat33:
    """Rotation matrix of the (w, x, y, z) quaternion ``q`` (normalized here)."""
    qn = q / wp.sqrt(wp.dot(q, q))
    w = qn[0]
    x = qn[1]
    y = qn[2]
    z = qn[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    )


@wp.kernel(enable_backward=True)
def _project(
    means: wp.array[wp.vec3],
    log_scales: wp.array[wp.vec3],
    quats: wp.array[wp.vec4],
    deform: wp.array[wp.mat33],
    opacity_logits: wp.array[float],
    w2c: wp.array[wp.mat44],
    intr: wp.array[wp.vec4],
    n: int,
    width: int,
    height: int,
    near: float,
    xy_depth: wp.array[wp.vec4],
    conic_opacity: wp.array[wp.vec4],
):
    """Per (camera, Gaussian): ``xy_depth = (u, v, z, valid)``, ``conic_opacity = (a, b, c, o)``.

    ``(a, b, c)`` is the inverse of the low-passed 2D covariance ``[[a, b], [b, c]]`` in px^-2,
    ``o`` the sigmoid opacity; culled Gaussians get all zeros (``valid = 0``).
    """
    tid = wp.tid()
    cam = tid // n
    g = tid - cam * n
    T = w2c[cam]
    m = means[g]
    x = T[0, 0] * m[0] + T[0, 1] * m[1] + T[0, 2] * m[2] + T[0, 3]
    y = T[1, 0] * m[0] + T[1, 1] * m[1] + T[1, 2] * m[2] + T[1, 3]
    z = T[2, 0] * m[0] + T[2, 1] * m[1] + T[2, 2] * m[2] + T[2, 3]
    if z <= near:
        xy_depth[tid] = wp.vec4(0.0)
        conic_opacity[tid] = wp.vec4(0.0)
        return
    k = intr[cam]
    fx = k[0]
    fy = k[1]
    cx = k[2]
    cy = k[3]

    R = _quat_to_rotmat(quats[g])
    s = log_scales[g]
    S = wp.mat33(wp.exp(s[0]), 0.0, 0.0, 0.0, wp.exp(s[1]), 0.0, 0.0, 0.0, wp.exp(s[2]))
    L = deform[g] * R * S

    # the reference's (gsplat's) clamp: the frustum through the image edges widened by 30% of the
    # half field of view on each side; only the Jacobian sees the clamped values
    margin_x = _CLAMP_MARGIN_C * 0.5 * float(width) / fx
    margin_y = _CLAMP_MARGIN_C * 0.5 * float(height) / fy
    tx = z * wp.min(wp.max(x / z, -(cx / fx + margin_x)), (float(width) - cx) / fx + margin_x)
    ty = z * wp.min(wp.max(y / z, -(cy / fy + margin_y)), (float(height) - cy) / fy + margin_y)
    rz = 1.0 / z
    J = wp.mat33(fx * rz, 0.0, -fx * tx * rz * rz, 0.0, fy * rz, -fy * ty * rz * rz, 0.0, 0.0, 0.0)
    Rc = wp.mat33(T[0, 0], T[0, 1], T[0, 2], T[1, 0], T[1, 1], T[1, 2], T[2, 0], T[2, 1], T[2, 2])
    A = J * Rc * L
    cov = A * wp.transpose(A)
    c00 = cov[0, 0] + _LOW_PASS
    c01 = cov[0, 1]
    c11 = cov[1, 1] + _LOW_PASS
    det = c00 * c11 - c01 * c01
    if det <= 0.0:
        xy_depth[tid] = wp.vec4(0.0)
        conic_opacity[tid] = wp.vec4(0.0)
        return
    inv_det = 1.0 / det
    opacity = 1.0 / (1.0 + wp.exp(-opacity_logits[g]))
    xy_depth[tid] = wp.vec4(fx * x * rz + cx, fy * y * rz + cy, z, 1.0)
    conic_opacity[tid] = wp.vec4(c11 * inv_det, -c01 * inv_det, c00 * inv_det, opacity)


@wp.kernel
def _count_tiles(
    xy_depth: wp.array[wp.vec4],
    conic_opacity: wp.array[wp.vec4],
    width: int,
    height: int,
    tile_edge: int,
    counts: wp.array[wp.int32],
    rects: wp.array[wp.vec4i],
):
    """Tile rectangle ``[x0, x1) x [y0, y1)`` covering every pixel centre the Gaussian can reach.

    A pixel is reached iff ``o exp(-q/2) >= 1/255`` with ``q = d^T Sigma'^-1 d``, i.e. inside the
    ellipse ``q <= 2 ln(255 o)``, whose half-extents are ``sqrt(2 ln(255 o) Sigma'_xx)`` and
    ``sqrt(2 ln(255 o) Sigma'_yy)``.
    """
    tid = wp.tid()
    p = xy_depth[tid]
    co = conic_opacity[tid]
    counts[tid] = 0
    rects[tid] = wp.vec4i(0, 0, 0, 0)
    if p[3] == 0.0 or co[3] < _ALPHA_MIN:
        return
    thr = 2.0 * (_LOG255 + wp.log(co[3]))
    if thr <= 0.0:
        return
    det_c = co[0] * co[2] - co[1] * co[1]
    if det_c <= 0.0:
        return
    ext_x = wp.sqrt(thr * co[2] / det_c) * (1.0 + _BBOX_PAD_C) + 1.0e-3
    ext_y = wp.sqrt(thr * co[0] / det_c) * (1.0 + _BBOX_PAD_C) + 1.0e-3
    # pixel i (centre i + 0.5) is inside iff |i + 0.5 - u| <= ext
    fw = float(width)
    fh = float(height)
    px0 = wp.clamp(wp.ceil(p[0] - ext_x - 0.5), 0.0, fw)
    px1 = wp.clamp(wp.floor(p[0] + ext_x - 0.5), -1.0, fw - 1.0)
    py0 = wp.clamp(wp.ceil(p[1] - ext_y - 0.5), 0.0, fh)
    py1 = wp.clamp(wp.floor(p[1] + ext_y - 0.5), -1.0, fh - 1.0)
    if px1 < px0 or py1 < py0:
        return
    tx0 = int(px0) // tile_edge
    tx1 = int(px1) // tile_edge + 1
    ty0 = int(py0) // tile_edge
    ty1 = int(py1) // tile_edge + 1
    counts[tid] = wp.int32((tx1 - tx0) * (ty1 - ty0))
    rects[tid] = wp.vec4i(tx0, ty0, tx1, ty1)


@wp.kernel
def _write_keys(
    xy_depth: wp.array[wp.vec4],
    counts: wp.array[wp.int32],
    offsets: wp.array[wp.int32],
    rects: wp.array[wp.vec4i],
    n: int,
    tiles_x: int,
    n_tiles: int,
    keys: wp.array[wp.int64],
    values: wp.array[wp.int32],
):
    """One key ``(camera * n_tiles + tile) << 32 | bits(z)`` per overlap; value: camera * N + Gaussian."""
    tid = wp.tid()
    cnt = counts[tid]
    if cnt == 0:
        return
    off = offsets[tid] - cnt  # offsets is the inclusive prefix sum
    cam = tid // n
    r = rects[tid]
    zbits = wp.int64(wp.cast(xy_depth[tid][2], wp.int32))  # z > 0: the sign bit is clear
    for ty in range(r[1], r[3]):
        for tx in range(r[0], r[2]):
            blk = wp.int64(cam * n_tiles + ty * tiles_x + tx)
            keys[off] = blk * wp.int64(4294967296) + zbits
            values[off] = wp.int32(tid)
            off += 1


@wp.kernel
def _tile_ranges(keys: wp.array[wp.int64], count: int, ranges: wp.array2d[wp.int32]):
    """``ranges[camera * n_tiles + tile] = [start, end)`` in the sorted overlap list."""
    k = wp.tid()
    blk = int(keys[k] // wp.int64(4294967296))
    if k == 0:
        ranges[blk, 0] = 0
    else:
        prev = int(keys[k - 1] // wp.int64(4294967296))
        if prev != blk:
            ranges[prev, 1] = k
            ranges[blk, 0] = k
    if k == count - 1:
        ranges[blk, 1] = count


@wp.func
def _splat_alpha(a: wp.vec4, co: wp.vec4, pcx: float, pcy: float):
    """Alpha of a splat at pixel centre (pcx, pcy), exactly as in :mod:`renderers.base`.

    Args:
        a: (u, v, z, valid) of the splat, pixels and metres.
        co: (conic a, conic b, conic c, opacity).

    Returns:
        ``alpha`` (0 when below 1/255, else ``min(0.99, o G)``), ``o G`` before the clamp, the
        falloff ``G = exp(-d^T conic d / 2)`` and ``d = (pcx - u, pcy - v)``.
    """
    dx = pcx - a[0]
    dy = pcy - a[1]
    G = wp.exp(-0.5 * (co[0] * dx * dx + co[2] * dy * dy) - co[1] * dx * dy)
    raw = co[3] * G
    alpha = wp.min(_ALPHA_MAX, raw)
    if alpha < _ALPHA_MIN:
        alpha = 0.0
    return alpha, raw, G, dx, dy


@wp.func
def _splat_grads(
    a: wp.vec4, co: wp.vec4, c: wp.vec3, pcx: float, pcy: float,
    T: float, S: wp.vec3, SD: float, SA: float, gC: wp.vec3, gD: float, gA: float,
):  # fmt: skip
    """One back-to-front step of the backward pass at one pixel.

    ``T`` is the transmittance after this splat; ``S``, ``SD``, ``SA`` the colour (background
    included), depth and alpha composited behind it, normalized by ``T``; ``gC``, ``gD``, ``gA``
    the pixel's output cotangents. With ``T_i = T / (1 - alpha)``:
    ``dL/dalpha = T_i (gC.(c - S) + gD (z - SD) + gA (1 - SA))``.

    Returns:
        ``(contributes, T_i, S', SD', SA', g_a, g_b, g_c)``: the state in front of this splat and
        the gradients w.r.t. ``(u, v, z, -)``, ``(conic a, b, c, opacity)`` and the colour
        (zeros when the splat does not contribute at this pixel).
    """
    alpha, raw, G, dx, dy = _splat_alpha(a, co, pcx, pcy)
    if alpha == 0.0:
        return int(0), T, S, SD, SA, wp.vec4(0.0), wp.vec4(0.0), wp.vec3(0.0)
    T_i = T / (1.0 - alpha)
    w = alpha * T_i
    dl_dalpha = T_i * (wp.dot(gC, c - S) + gD * (a[2] - SD) + gA * (1.0 - SA))
    g_op = float(0.0)
    g_pow = float(0.0)
    if raw <= _ALPHA_MAX:  # the clamp at 0.99 cuts the gradient
        g_op = G * dl_dalpha
        g_pow = raw * dl_dalpha
    g_a = wp.vec4(g_pow * (co[0] * dx + co[1] * dy), g_pow * (co[1] * dx + co[2] * dy), w * gD, 0.0)
    g_b = wp.vec4(-0.5 * g_pow * dx * dx, -g_pow * dx * dy, -0.5 * g_pow * dy * dy, g_op)
    return (
        int(1),
        T_i,
        alpha * c + (1.0 - alpha) * S,
        alpha * a[2] + (1.0 - alpha) * SD,
        alpha + (1.0 - alpha) * SA,
        g_a,
        g_b,
        w * gC,
    )


@wp.kernel
def _raster_fwd(
    ranges: wp.array2d[wp.int32],
    sorted_ids: wp.array[wp.int32],
    xy_depth: wp.array[wp.vec4],
    conic_opacity: wp.array[wp.vec4],
    colors: wp.array[wp.vec3],
    width: int,
    height: int,
    tiles_x: int,
    n_tiles: int,
    tile_edge: int,
    background: wp.vec3,
    out_rgb: wp.array[wp.vec3],
    out_alpha: wp.array[float],
    out_depth: wp.array[float],
    out_T: wp.array[float],
    out_count: wp.array[wp.int32],
):
    """Front-to-back compositing, one block per (camera, tile), pixels spread over the lanes.

    Blocks of several lanes (CUDA) gather the tile's list into shared memory 256 splats at a time
    and leave once every pixel is done; a one-lane block (CPU) reads the list directly.
    """
    blk, lane = wp.tid()
    bd = wp.block_dim()
    cam = blk // n_tiles
    tile = blk - cam * n_tiles
    ty = tile // tiles_x
    tx = tile - ty * tiles_x
    start = ranges[blk, 0]
    end = ranges[blk, 1]
    for ps in range(tile_edge * tile_edge // bd):
        p = ps * bd + lane
        px = tx * tile_edge + p % tile_edge
        py = ty * tile_edge + p // tile_edge
        inside = px < width and py < height
        pcx = float(px) + 0.5
        pcy = float(py) + 0.5
        T = float(1.0)
        C = wp.vec3(0.0)
        D = float(0.0)
        used = int(0)
        if bd == 1:
            if inside:
                for k in range(start, end):
                    gid = sorted_ids[k]
                    a = xy_depth[gid]
                    alpha, raw, G, dx, dy = _splat_alpha(a, conic_opacity[gid], pcx, pcy)
                    if alpha > 0.0:
                        next_T = T * (1.0 - alpha)
                        if next_T < _T_MIN:
                            break
                        w = alpha * T
                        C = C + w * colors[gid]
                        D = D + w * a[2]
                        T = next_T
                        used = k - start + 1
        else:
            done = int(1)
            if inside:
                done = 0
            for b in range((end - start + _BATCH - 1) // _BATCH):
                if wp.tile_extract(wp.tile_sum(wp.tile(done)), 0) == bd:
                    break
                k0 = start + b * _BATCH
                ids = wp.tile_load(sorted_ids, shape=_BATCH, offset=k0, storage="shared")
                t_a = wp.tile_load_indexed(xy_depth, indices=ids, shape=(_BATCH,), axis=0, storage="shared")
                t_b = wp.tile_load_indexed(conic_opacity, indices=ids, shape=(_BATCH,), axis=0, storage="shared")
                t_c = wp.tile_load_indexed(colors, indices=ids, shape=(_BATCH,), axis=0, storage="shared")
                if done == 0:
                    for j in range(wp.min(_BATCH, end - k0)):
                        a = wp.tile_extract(t_a, j)
                        alpha, raw, G, dx, dy = _splat_alpha(a, wp.tile_extract(t_b, j), pcx, pcy)
                        if alpha > 0.0:
                            next_T = T * (1.0 - alpha)
                            if next_T < _T_MIN:
                                done = 1
                                break
                            w = alpha * T
                            C = C + w * wp.tile_extract(t_c, j)
                            D = D + w * a[2]
                            T = next_T
                            used = k0 - start + j + 1
        if inside:
            pix = (cam * height + py) * width + px
            out_rgb[pix] = C + T * background
            out_alpha[pix] = 1.0 - T
            out_depth[pix] = D
            out_T[pix] = T
            out_count[pix] = wp.int32(used)


@wp.kernel
def _raster_bwd(
    ranges: wp.array2d[wp.int32],
    sorted_ids: wp.array[wp.int32],
    xy_depth: wp.array[wp.vec4],
    conic_opacity: wp.array[wp.vec4],
    colors: wp.array[wp.vec3],
    width: int,
    height: int,
    tiles_x: int,
    n_tiles: int,
    tile_edge: int,
    background: wp.vec3,
    out_T: wp.array[float],
    out_count: wp.array[wp.int32],
    g_rgb: wp.array[wp.vec3],
    g_alpha: wp.array[float],
    g_depth: wp.array[float],
    g_xy_depth: wp.array[wp.vec4],
    g_conic_opacity: wp.array[wp.vec4],
    g_colors: wp.array[wp.vec3],
):
    """Back-to-front replay of :func:`_raster_fwd`; accumulates gradients per camera-splat.

    Each pixel starts from its saved final transmittance and list count. Blocks of several lanes
    walk the longest count of the block in shared-memory batches and sum each splat's gradient
    over every 32-lane warp before one atomic add; a one-lane block adds per pixel.
    """
    blk, lane = wp.tid()
    bd = wp.block_dim()
    cam = blk // n_tiles
    tile = blk - cam * n_tiles
    ty = tile // tiles_x
    tx = tile - ty * tiles_x
    start = ranges[blk, 0]
    for ps in range(tile_edge * tile_edge // bd):
        p = ps * bd + lane
        px = tx * tile_edge + p % tile_edge
        py = ty * tile_edge + p // tile_edge
        inside = px < width and py < height
        pcx = float(px) + 0.5
        pcy = float(py) + 0.5
        T = float(1.0)
        n_used = int(0)
        gC = wp.vec3(0.0)
        gA = float(0.0)
        gD = float(0.0)
        if inside:
            pix = (cam * height + py) * width + px
            T = out_T[pix]
            n_used = int(out_count[pix])
            gC = g_rgb[pix]
            gA = g_alpha[pix]
            gD = g_depth[pix]
        S = background
        SD = float(0.0)
        SA = float(0.0)
        if bd == 1:
            for kk in range(n_used):
                gid = sorted_ids[start + n_used - 1 - kk]
                contrib, T, S, SD, SA, g_a, g_b, g_c = _splat_grads(
                    xy_depth[gid], conic_opacity[gid], colors[gid], pcx, pcy, T, S, SD, SA, gC, gD, gA
                )
                if contrib != 0:
                    wp.atomic_add(g_xy_depth, gid, g_a)
                    wp.atomic_add(g_conic_opacity, gid, g_b)
                    wp.atomic_add(g_colors, gid, g_c)
        else:
            max_used = wp.tile_extract(wp.tile_max(wp.tile(n_used)), 0)
            n_batches = (max_used + _BATCH - 1) // _BATCH
            for bi in range(n_batches):
                k0 = (n_batches - 1 - bi) * _BATCH  # relative to start
                ids = wp.tile_load(sorted_ids, shape=_BATCH, offset=start + k0, storage="shared")
                t_a = wp.tile_load_indexed(xy_depth, indices=ids, shape=(_BATCH,), axis=0, storage="shared")
                t_b = wp.tile_load_indexed(conic_opacity, indices=ids, shape=(_BATCH,), axis=0, storage="shared")
                t_c = wp.tile_load_indexed(colors, indices=ids, shape=(_BATCH,), axis=0, storage="shared")
                cnt = wp.min(_BATCH, max_used - k0)
                for jj in range(cnt):
                    j = cnt - 1 - jj
                    contrib = int(0)
                    g_a = wp.vec4(0.0)
                    g_b = wp.vec4(0.0)
                    g_c = wp.vec3(0.0)
                    if k0 + j < n_used:
                        contrib, T, S, SD, SA, g_a, g_b, g_c = _splat_grads(
                            wp.tile_extract(t_a, j), wp.tile_extract(t_b, j), wp.tile_extract(t_c, j),
                            pcx, pcy, T, S, SD, SA, gC, gD, gA,
                        )  # fmt: skip
                    if _warp_any(contrib) != 0:  # warp-uniform: every lane joins the shuffles
                        g_a = _warp_sum4(g_a)
                        g_b = _warp_sum4(g_b)
                        g_c = _warp_sum3(g_c)
                        if _warp_flush(contrib) != 0:
                            gid = wp.tile_extract(ids, j)
                            wp.atomic_add(g_xy_depth, gid, g_a)
                            wp.atomic_add(g_conic_opacity, gid, g_b)
                            wp.atomic_add(g_colors, gid, g_c)


# ---------------------------------------------------------------------------------------------
# Host side


def _wa(t: torch.Tensor, dtype=None):
    """Zero-copy kernel-argument descriptor of a contiguous torch tensor (cheaper than a wp.array).

    Launches that take it must run inside :func:`_warp_scope` (the descriptor has no device).
    """
    return wp.from_torch(t, dtype=dtype, requires_grad=False, return_ctype=True)


_STREAMS: dict[tuple[int, int], wp.Stream] = {}


def tile_size(device: torch.device) -> int:
    """Tile edge in pixels for rendering on ``device``.

    CUDA blocks (and CPU blocks when ``wp.config.enable_cpu_blocks`` is set) give one lane to
    each pixel of a :data:`TILE_SIZE` tile. A one-lane CPU block walks its tile's list once per
    pixel, so smaller tiles, whose lists hold only the splats that reach them, cost less there
    (on one core, 2,500 Gaussians in 3 views: 6.3x faster at 32 px, 2.9x at 64 px). Images are identical for any edge.
    """
    if device.type == "cuda" or getattr(wp.config, "enable_cpu_blocks", False):
        return TILE_SIZE
    return CPU_TILE_SIZE


def _warp_scope(device: torch.device):
    """Context manager that makes Warp launch on ``device`` (on CUDA: torch's current stream)."""
    if device.type == "cuda":
        ts = torch.cuda.current_stream(device)
        key = (ts.device.index, ts.cuda_stream)
        stream = _STREAMS.get(key)
        if stream is None:
            stream = wp.stream_from_torch(ts)
            _STREAMS[key] = stream
        return wp.ScopedStream(stream, sync_enter=False)
    return wp.ScopedDevice(wp.device_from_torch(device))


class _Binning:
    """Sorted Gaussian-tile overlaps of one forward call (not differentiated)."""

    def __init__(self, sorted_ids: torch.Tensor, ranges: torch.Tensor):
        self.sorted_ids = sorted_ids  # (M,) int32: camera * N + Gaussian, by (camera, tile, depth)
        self.ranges = ranges  # (B * n_tiles, 2) int32


def _bin(
    xy_depth: torch.Tensor, conic_opacity: torch.Tensor, B: int, N: int, width: int, height: int, device, edge: int
) -> _Binning:
    tiles_x = (width + edge - 1) // edge
    tiles_y = (height + edge - 1) // edge
    n_tiles = tiles_x * tiles_y
    counts = torch.empty(B * N, dtype=torch.int32, device=device)
    rects = torch.empty(B * N, 4, dtype=torch.int32, device=device)
    wp.launch(
        _count_tiles,
        dim=B * N,
        inputs=[_wa(xy_depth, wp.vec4), _wa(conic_opacity, wp.vec4), width, height, edge],
        outputs=[_wa(counts), _wa(rects, wp.vec4i)],
    )
    offsets = torch.cumsum(counts, 0, dtype=torch.int64)
    M = int(offsets[-1])  # host sync: sizes the overlap buffers
    ranges = torch.zeros(B * n_tiles, 2, dtype=torch.int32, device=device)
    if M == 0:
        return _Binning(torch.zeros(1, dtype=torch.int32, device=device), ranges)
    if M >= 2**31 - 1:
        raise ValueError(f"too many Gaussian-tile overlaps ({M}) for 32-bit indexing; render fewer cameras per call")
    offsets = offsets.to(torch.int32)
    keys = torch.empty(2 * M, dtype=torch.int64, device=device)
    values = torch.empty(2 * M, dtype=torch.int32, device=device)
    wk, wv = wp.from_torch(keys, requires_grad=False), wp.from_torch(values, requires_grad=False)
    wp.launch(
        _write_keys,
        dim=B * N,
        inputs=[_wa(xy_depth, wp.vec4), _wa(counts), _wa(offsets), _wa(rects, wp.vec4i), N, tiles_x, n_tiles],
        outputs=[wk, wv],
    )
    end_bit = 32 + max(1, int(B * n_tiles - 1).bit_length())
    wp.utils.radix_sort_pairs(wk, wv, M, 0, end_bit)
    wp.launch(_tile_ranges, dim=M, inputs=[wk, M], outputs=[_wa(ranges)])
    return _Binning(values[:M], ranges)


class _RasterizeFunction(torch.autograd.Function):
    """Differentiable Warp rasterization; torch tensors in and out."""

    @staticmethod
    def forward(
        ctx,
        means: torch.Tensor,
        log_scales: torch.Tensor,
        quats: torch.Tensor,
        deformation: torch.Tensor,
        opacity_logits: torch.Tensor,
        colors: torch.Tensor,
        w2c: torch.Tensor,
        intr: torch.Tensor,
        settings: tuple,
    ):
        width, height, near, background = settings
        device = means.device
        N = means.shape[0]
        B = w2c.shape[0]
        edge = tile_size(device)
        tiles_x = (width + edge - 1) // edge
        n_tiles = tiles_x * ((height + edge - 1) // edge)
        xy_depth = torch.empty(B * N, 4, dtype=torch.float32, device=device)
        conic_opacity = torch.empty(B * N, 4, dtype=torch.float32, device=device)
        rgb = torch.empty(B, height, width, 3, dtype=torch.float32, device=device)
        alpha = torch.empty(B, height, width, dtype=torch.float32, device=device)
        depth = torch.empty(B, height, width, dtype=torch.float32, device=device)
        final_T = torch.empty(B, height, width, dtype=torch.float32, device=device)
        count = torch.empty(B, height, width, dtype=torch.int32, device=device)
        proj_args = [
            _wa(means, wp.vec3),
            _wa(log_scales, wp.vec3),
            _wa(quats, wp.vec4),
            _wa(deformation, wp.mat33),
            _wa(opacity_logits),
            _wa(w2c, wp.mat44),
            _wa(intr, wp.vec4),
            N,
            width,
            height,
            near,
        ]
        with _warp_scope(device):
            wp.launch(_project, dim=B * N, inputs=proj_args, outputs=[_wa(xy_depth, wp.vec4), _wa(conic_opacity, wp.vec4)])
            binning = _bin(xy_depth, conic_opacity, B, N, width, height, device, edge)
            wp.launch_tiled(
                _raster_fwd,
                dim=[B * n_tiles],
                inputs=[
                    _wa(binning.ranges),
                    _wa(binning.sorted_ids),
                    _wa(xy_depth, wp.vec4),
                    _wa(conic_opacity, wp.vec4),
                    _wa(colors.view(B * N, 3), wp.vec3),
                    width,
                    height,
                    tiles_x,
                    n_tiles,
                    edge,
                    wp.vec3(*background),
                ],
                outputs=[
                    _wa(rgb.view(-1, 3), wp.vec3),
                    _wa(alpha.view(-1)),
                    _wa(depth.view(-1)),
                    _wa(final_T.view(-1)),
                    _wa(count.view(-1)),
                ],
                block_dim=BATCH,
            )
        ctx.save_for_backward(
            means, log_scales, quats, deformation, opacity_logits, colors, w2c, intr,
            xy_depth, conic_opacity, binning.sorted_ids, binning.ranges, final_T, count,
        )  # fmt: skip
        ctx.settings = settings
        ctx.edge = edge
        return rgb, alpha, depth

    @staticmethod
    def backward(ctx, g_rgb: Optional[torch.Tensor], g_alpha: Optional[torch.Tensor], g_depth: Optional[torch.Tensor]):
        (means, log_scales, quats, deformation, opacity_logits, colors, w2c, intr,
         xy_depth, conic_opacity, sorted_ids, ranges, final_T, count) = ctx.saved_tensors  # fmt: skip
        width, height, near, background = ctx.settings
        device = means.device
        N = means.shape[0]
        B = w2c.shape[0]
        edge = ctx.edge
        tiles_x = (width + edge - 1) // edge
        n_tiles = tiles_x * ((height + edge - 1) // edge)

        def cotangent(g: Optional[torch.Tensor], shape: tuple) -> torch.Tensor:
            if g is None:
                return torch.zeros(shape, dtype=torch.float32, device=device)
            return g.to(torch.float32).contiguous()

        g_rgb = cotangent(g_rgb, (B, height, width, 3))
        g_alpha = cotangent(g_alpha, (B, height, width))
        g_depth = cotangent(g_depth, (B, height, width))
        g_xy_depth = torch.zeros(B * N, 4, dtype=torch.float32, device=device)
        g_conic_opacity = torch.zeros(B * N, 4, dtype=torch.float32, device=device)
        g_colors = torch.zeros(B, N, 3, dtype=torch.float32, device=device)
        g_means = torch.zeros_like(means)
        g_log_scales = torch.zeros_like(log_scales)
        g_quats = torch.zeros_like(quats)
        g_deformation = torch.zeros_like(deformation)
        g_logits = torch.zeros_like(opacity_logits)
        w_xy_depth = _wa(xy_depth, wp.vec4)
        w_conic_opacity = _wa(conic_opacity, wp.vec4)
        wg_xy_depth = _wa(g_xy_depth, wp.vec4)
        wg_conic_opacity = _wa(g_conic_opacity, wp.vec4)
        with _warp_scope(device):
            wp.launch_tiled(
                _raster_bwd,
                dim=[B * n_tiles],
                inputs=[
                    _wa(ranges),
                    _wa(sorted_ids),
                    w_xy_depth,
                    w_conic_opacity,
                    _wa(colors.view(B * N, 3), wp.vec3),
                    width,
                    height,
                    tiles_x,
                    n_tiles,
                    edge,
                    wp.vec3(*background),
                    _wa(final_T.view(-1)),
                    _wa(count.view(-1)),
                    _wa(g_rgb.view(-1, 3), wp.vec3),
                    _wa(g_alpha.view(-1)),
                    _wa(g_depth.view(-1)),
                ],
                outputs=[wg_xy_depth, wg_conic_opacity, _wa(g_colors.view(B * N, 3), wp.vec3)],
                block_dim=BATCH,
            )
            if not any(ctx.needs_input_grad[:5]):
                return None, None, None, None, None, g_colors, None, None, None
            wp.launch(
                _project,
                dim=B * N,
                inputs=[
                    _wa(means, wp.vec3),
                    _wa(log_scales, wp.vec3),
                    _wa(quats, wp.vec4),
                    _wa(deformation, wp.mat33),
                    _wa(opacity_logits),
                    _wa(w2c, wp.mat44),
                    _wa(intr, wp.vec4),
                    N,
                    width,
                    height,
                    near,
                ],
                outputs=[w_xy_depth, w_conic_opacity],
                adj_inputs=[
                    _wa(g_means, wp.vec3),
                    _wa(g_log_scales, wp.vec3),
                    _wa(g_quats, wp.vec4),
                    _wa(g_deformation, wp.mat33),
                    _wa(g_logits),
                    None,
                    None,
                    0,
                    0,
                    0,
                    0.0,
                ],
                adj_outputs=[wg_xy_depth, wg_conic_opacity],
                adjoint=True,
            )
        return g_means, g_log_scales, g_quats, g_deformation, g_logits, g_colors, None, None, None


def _deformation(gaussians: Gaussians) -> torch.Tensor:
    """(N, 3, 3) per-Gaussian deformation, the identity when the Gaussians have none."""
    if gaussians.deformation is not None:
        return gaussians.deformation
    return torch.eye(3, dtype=gaussians.means.dtype, device=gaussians.means.device).expand(len(gaussians), 3, 3)


@register_renderer("warp")
class WarpTileRenderer(Renderer):
    """Tile-based Warp rasterizer (CPU and CUDA), differentiable w.r.t. every Gaussian attribute.

    Computes in float32 whatever the input dtype (outputs are cast back to the dtype of
    ``gaussians.means``). Camera parameters get no gradient.

    Args:
        background: RGB background composited as ``rgb + (1 - alpha) * background``.
        validate: check the inputs (types, shapes, dtypes, NaNs, zero quaternions, cameras) on
            every call, with the same checks as the ``"torch"`` reference. They synchronize with
            the device; a training loop whose data is known to be valid may turn them off.
    """

    def __init__(self, background: tuple[float, float, float] = (0.0, 0.0, 0.0), validate: bool = True):
        super().__init__(background)
        self.validate = bool(validate)

    def render(self, gaussians: Gaussians, cameras: "Cameras") -> RenderOutput:
        """Render ``gaussians`` into every camera of ``cameras`` (one batched call).

        Args:
            gaussians: N Gaussians (world frame, metres).
            cameras: B cameras sharing width W and height H (moved to the Gaussians' device).

        Returns:
            rgb (B, H, W, 3), alpha (B, H, W), depth (B, H, W) (``sum_i w_i z_i``, metres).

        Raises:
            TypeError: ``gaussians`` or ``cameras`` of the wrong type.
            ValueError: wrong shapes, mixed dtypes or devices, NaN/inf values, zero quaternions.
        """
        if self.validate:
            validate_render_inputs(gaussians, cameras)
        dtype, device = gaussians.means.dtype, gaussians.means.device
        cameras = cameras.to(device)
        B, N, H, W = len(cameras), len(gaussians), cameras.height, cameras.width
        if N == 0:
            # keep the outputs attached to the (empty) inputs so that backward() still works
            anchor = (gaussians.means.sum() + gaussians.opacity_logits.sum()) * 0.0
            bg = torch.tensor(self.background, dtype=dtype, device=device)
            return RenderOutput(
                rgb=bg.expand(B, H, W, 3) + anchor,
                alpha=torch.zeros(B, H, W, dtype=dtype, device=device) + anchor,
                depth=torch.zeros(B, H, W, dtype=dtype, device=device) + anchor,
            )
        wp.init()  # no-op once initialized
        f32 = torch.float32
        colors = gaussian_colors(gaussians, cameras).to(f32).contiguous()  # (B, N, 3)
        K = cameras.K.detach().to(f32)
        intr = torch.stack([K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]], -1).contiguous()
        w2c = cameras.w2c.detach().to(f32).contiguous()
        settings = (int(W), int(H), float(cameras.near), tuple(self.background))
        rgb, alpha, depth = _RasterizeFunction.apply(
            gaussians.means.to(f32).contiguous(),
            gaussians.log_scales.to(f32).contiguous(),
            gaussians.quats.to(f32).contiguous(),
            _deformation(gaussians).to(f32).contiguous(),
            gaussians.opacity_logits.to(f32).contiguous(),
            colors,
            w2c,
            intr,
            settings,
        )
        if dtype != f32:
            rgb, alpha, depth = rgb.to(dtype), alpha.to(dtype), depth.to(dtype)
        return RenderOutput(rgb=rgb, alpha=alpha, depth=depth)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(background={self.background}, validate={self.validate})"
