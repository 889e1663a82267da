"""Point-cloud metrics: Chamfer distance and Earth Mover's distance (ProJo4D evaluator), and the
differentiable Chamfer loss used for fitting.

Evaluation protocol (ProJo4D ``utils/eval.py::evaluate``, which follows Spring-Gaus):

* One :class:`random.Random` stream seeded once per *sequence* (seed 0); for every frame the
  prediction's indices are drawn first, then the ground truth's, with ``random.sample`` (no
  replacement). Both clouds of a frame get the same count
  ``n = min(n_max, N_pred, N_gt)``, with ``n_max`` = 8192 for CD and 2048 for EMD. Feeding the
  same clouds in the same order therefore reproduces the evaluator's subsets exactly.
* CD: squared nearest-neighbour distances, mean per direction, sum of both directions, x 1e3
  (``pytorch3d.loss.chamfer_distance`` defaults, times 1e3).
* EMD: exact one-to-one assignment (``scipy.optimize.linear_sum_assignment``) on Euclidean,
  *unsquared* distances, mean matched distance.
* Sequence scores are plain means over frames; :func:`split_mean` gives the training-frame and
  future-frame means the paper reports.

Units follow the clouds (the datasets use metres); CD is in squared units x 1e3.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Literal

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

__all__ = [
    "CD_MAX_POINTS",
    "EMD_POINTS",
    "chamfer_distance",
    "chamfer_sequence",
    "earth_movers_distance",
    "emd_sequence",
    "emd_per_frame",
    "mean_nearest_distance",
    "chamfer_loss",
    "split_mean",
]

CD_MAX_POINTS = 8192  # the evaluator's 4 * n_samples with n_samples = 2048
EMD_POINTS = 2048

SeedLike = int | random.Random


def _points(cloud, name: str) -> np.ndarray:
    """Return ``cloud`` as a float64 (N, 3) array; accepts numpy arrays, torch tensors, lists."""
    if isinstance(cloud, torch.Tensor):
        cloud = cloud.detach().cpu().double().numpy()
    arr = np.asarray(cloud, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError(f"{name} is empty")
    return arr


def _rng(seed: SeedLike) -> random.Random:
    return seed if isinstance(seed, random.Random) else random.Random(seed)


def _subsample_pair(
    pred: np.ndarray, gt: np.ndarray, n_max: int | None, rng: random.Random
) -> tuple[np.ndarray, np.ndarray]:
    """Draw ``min(n_max, N_pred, N_gt)`` points from each cloud, prediction first (evaluator order)."""
    if n_max is None:
        return pred, gt
    n = min(n_max, pred.shape[0], gt.shape[0])
    pred = pred[rng.sample(range(pred.shape[0]), n)]
    gt = gt[rng.sample(range(gt.shape[0]), n)]
    return pred, gt


def _chamfer_np(a: np.ndarray, b: np.ndarray) -> float:
    d_ab, _ = cKDTree(b).query(a, k=1)
    d_ba, _ = cKDTree(a).query(b, k=1)
    return float(np.mean(d_ab**2) + np.mean(d_ba**2))


def mean_nearest_distance(a, b) -> float:
    """Half the sum of the two mean nearest-neighbour distances between point sets ``a`` (N, 3)
    and ``b`` (M, 3): the symmetric Chamfer distance in the clouds' own (unsquared) units, every
    point used (unlike :func:`chamfer_distance`, which squares and subsamples as ProJo4D reports)."""
    a, b = _points(a, "a"), _points(b, "b")
    return 0.5 * float(cKDTree(b).query(a, k=1)[0].mean() + cKDTree(a).query(b, k=1)[0].mean())


def chamfer_distance(
    pred, gt, *, max_points: int | None = CD_MAX_POINTS, seed: SeedLike = 0
) -> float:
    """Chamfer distance between two point clouds of one frame, as ProJo4D reports it.

    Args:
        pred: Predicted points, (N, 3) array or tensor.
        gt: Ground-truth points, (M, 3).
        max_points: Both clouds are subsampled (without replacement) to
            ``min(max_points, N, M)`` points; ``None`` keeps every point.
        seed: Seed of the :class:`random.Random` stream, or a stream to continue (what
            :func:`chamfer_sequence` does to match the evaluator across frames).

    Returns:
        ``(mean_a min_b |a-b|^2 + mean_b min_a |a-b|^2) * 1e3``.
    """
    p, g = _subsample_pair(_points(pred, "pred"), _points(gt, "gt"), max_points, _rng(seed))
    return _chamfer_np(p, g) * 1e3


def earth_movers_distance(
    pred,
    gt,
    *,
    n_points: int = EMD_POINTS,
    seed: SeedLike = 0,
    fewer: Literal["shrink", "replace"] = "shrink",
) -> float:
    """Earth Mover's distance between two point clouds of one frame, as ProJo4D reports it.

    Args:
        pred: Predicted points, (N, 3).
        gt: Ground-truth points, (M, 3).
        n_points: Number of points matched per cloud.
        seed: Seed of the :class:`random.Random` stream, or a stream to continue.
        fewer: What happens when a cloud has fewer than ``n_points`` points.
            ``"shrink"`` (default, the evaluator's rule): both clouds are subsampled without
            replacement to ``min(n_points, N, M)``. ``"replace"``: each cloud is sampled to
            exactly ``n_points``, with replacement only for a cloud that has fewer points
            (drawn with ``random.choices`` from the same stream); numbers then differ from the
            paper's for small clouds.

    Returns:
        Mean Euclidean (unsquared) distance over the optimal one-to-one assignment.
    """
    return _assignment_mean(*_emd_pair(pred, gt, n_points, _rng(seed), fewer))


def _emd_pair(pred, gt, n_points: int, rng: random.Random, fewer: str) -> tuple[np.ndarray, np.ndarray]:
    """The two subsampled clouds that :func:`earth_movers_distance` matches (draws from ``rng``)."""
    p, g = _points(pred, "pred"), _points(gt, "gt")
    if fewer == "shrink":
        return _subsample_pair(p, g, n_points, rng)
    if fewer == "replace":
        return _sample_exact(p, n_points, rng), _sample_exact(g, n_points, rng)
    raise ValueError(f"fewer must be 'shrink' or 'replace', got {fewer!r}")


def _assignment_mean(p: np.ndarray, g: np.ndarray) -> float:
    """Mean Euclidean distance of the optimal one-to-one assignment of ``p`` to ``g``."""
    cost = cdist(p, g)
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].mean())


def _sample_exact(cloud: np.ndarray, n: int, rng: random.Random) -> np.ndarray:
    if cloud.shape[0] >= n:
        return cloud[rng.sample(range(cloud.shape[0]), n)]
    return cloud[rng.choices(range(cloud.shape[0]), k=n)]


def _check_lengths(preds: Sequence, gts: Sequence) -> None:
    if len(preds) != len(gts):
        raise ValueError(f"{len(preds)} predicted frames but {len(gts)} ground-truth frames")
    if len(preds) == 0:
        raise ValueError("no frames to evaluate")


def chamfer_sequence(
    preds: Sequence, gts: Sequence, *, max_points: int | None = CD_MAX_POINTS, seed: int = 0
) -> tuple[float, list[float]]:
    """Chamfer distance of every frame of a sequence, one random stream for the whole sequence.

    Args:
        preds: T predicted clouds, each (N_t, 3).
        gts: T ground-truth clouds, each (M_t, 3).
        max_points: See :func:`chamfer_distance`.
        seed: Seed of the sequence's random stream (the evaluator uses 0).

    Returns:
        ``(mean over frames, per-frame list)``.
    """
    _check_lengths(preds, gts)
    rng = random.Random(seed)
    values = [chamfer_distance(p, g, max_points=max_points, seed=rng) for p, g in zip(preds, gts)]
    return float(np.mean(values)), values


def emd_sequence(
    preds: Sequence,
    gts: Sequence,
    *,
    n_points: int = EMD_POINTS,
    seed: int = 0,
    fewer: Literal["shrink", "replace"] = "shrink",
    workers: int | None = None,
) -> tuple[float, list[float]]:
    """Earth Mover's distance of every frame of a sequence (see :func:`chamfer_sequence`).

    ``workers`` threads solve the frames' assignments (default: see :func:`emd_per_frame`); the
    values do not depend on it.

    Returns:
        ``(mean over frames, per-frame list)``.
    """
    _check_lengths(preds, gts)
    values = emd_per_frame(preds, gts, n_points=n_points, seed=seed, fewer=fewer, workers=workers)
    return float(np.mean(values)), values


def emd_per_frame(
    preds: Sequence,
    gts: Sequence,
    *,
    n_points: int = EMD_POINTS,
    seed: int | random.Random = 0,
    fewer: Literal["shrink", "replace"] = "shrink",
    workers: int | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> list[float]:
    """:func:`earth_movers_distance` of every frame, the subsets drawn in frame order from one
    stream (the evaluator's), the assignments solved on ``workers`` threads (scipy's solver
    releases the GIL). The default is this run's share of the cores
    (:func:`toolkit.threads.resolve_threads` without its CPU cap of 1: ``PROJO4D_THREADS`` when a
    benchmark set it, else the affinity-mask cores over ``PROJO4D_CONCURRENT_RUNS``), since these
    are a few large independent tasks, not torch's small OpenMP regions. The values do not depend
    on ``workers``. ``on_frame(t)`` is called in frame order once frame ``t``'s value is known."""
    _check_lengths(preds, gts)
    rng = _rng(seed)
    pairs = [_emd_pair(p, g, n_points, rng, fewer) for p, g in zip(preds, gts)]
    if workers is None:
        from toolkit.threads import available_cores, resolve_threads

        workers = resolve_threads(cap=available_cores()).threads
    workers = max(1, min(len(pairs), workers))
    values: list[float] = []
    with ThreadPoolExecutor(workers) as pool:
        for t, future in enumerate([pool.submit(_assignment_mean, *pair) for pair in pairs]):
            values.append(future.result())
            if on_frame is not None:
                on_frame(t)
    return values


def split_mean(values: Sequence[float], n_train: int) -> tuple[float, float]:
    """Means over the training frames ``[0, n_train)`` and the future frames ``[n_train, T)``.

    A part without frames gives ``nan`` (the ProJo4D evaluator writes 0.0 there).
    """
    if n_train < 0:
        raise ValueError(f"n_train must be >= 0, got {n_train}")
    vals = np.asarray(values, dtype=np.float64)
    train, future = vals[:n_train], vals[n_train:]
    return (
        float(train.mean()) if train.size else float("nan"),
        float(future.mean()) if future.size else float("nan"),
    )


def _nn_sq_dist(a: torch.Tensor, b: torch.Tensor, chunk_elements: int) -> torch.Tensor:
    """Differentiable squared distance from each row of ``a`` to its nearest row of ``b``.

    The nearest neighbour is found chunk by chunk without autograd (memory O(chunk x M)), then the
    squared distance of the matched pairs is recomputed exactly with autograd (memory O(N)). The
    gradient equals that of ``min_j |a_i - b_j|^2`` wherever the minimum is unique.
    """
    rows = max(1, chunk_elements // max(1, b.shape[0]))
    with torch.no_grad():
        idx = torch.cat(
            [torch.cdist(a[i : i + rows], b).argmin(dim=1) for i in range(0, a.shape[0], rows)]
        )
    return ((a - b[idx]) ** 2).sum(dim=-1)


def chamfer_loss(x: torch.Tensor, y: torch.Tensor, *, chunk_elements: int = 1 << 24) -> torch.Tensor:
    """Symmetric Chamfer loss for fitting (not x 1e3, no subsampling).

    Args:
        x: (N, 3) points, any device and float dtype.
        y: (M, 3) points on the same device.
        chunk_elements: Upper bound on the elements of one distance block (rows are chunked so
            that ``rows * M <= chunk_elements``); bounds memory on CPU and CUDA.

    Returns:
        Scalar ``mean_i min_j |x_i - y_j|^2 + mean_j min_i |x_i - y_j|^2``; gradients flow to both
        inputs.
    """
    for name, t in (("x", x), ("y", y)):
        if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] == 0:
            raise ValueError(f"{name} must have shape (N, 3) with N > 0, got {tuple(t.shape)}")
    return _nn_sq_dist(x, y, chunk_elements).mean() + _nn_sq_dist(y, x, chunk_elements).mean()
