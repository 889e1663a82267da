"""Batches of (camera, frame) views of one scene: a torch Dataset and a Lightning DataModule.

Protocol defaults (paper, Sec. "Experimental Settings"; DESIGN section 8): fit on cameras 2, 6
and 10 in 1-based numbering (0-based indices 1, 5, 9; ProJo4D's ``--cam_idxs 1 5 9``), the rest
are held out; frames ``[0, n_train)`` fit (n_train = 14), later frames are the future.
All indices in this module are 0-based.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytorch_lightning as pl
import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader, Dataset, Sampler

from toolkit.cameras import Cameras
from toolkit.data.errors import DatasetError
from toolkit.data.layout import load_scene
from toolkit.data.scene import MultiViewScene

__all__ = [
    "SPARSE_VIEW_CAMERAS",
    "SPARSE_VIEW_CAMERAS_ONE_BASED",
    "DEFAULT_N_TRAIN",
    "MultiViewDataset",
    "CameraFrameBatchSampler",
    "MultiViewDataModule",
    "collate_views",
    "resolve_cameras",
]

SPARSE_VIEW_CAMERAS_ONE_BASED = (2, 6, 10)
SPARSE_VIEW_CAMERAS = tuple(c - 1 for c in SPARSE_VIEW_CAMERAS_ONE_BASED)
DEFAULT_N_TRAIN = 14


def resolve_cameras(scene: MultiViewScene, cameras: Sequence[int] | str) -> list[int]:
    """0-based camera indices from ``"sparse"`` (1, 5, 9), ``"all"`` or an explicit list.

    Raises:
        DatasetError: An index does not exist (the message lists the valid range), or a list
            is empty or has duplicates.
    """
    if isinstance(cameras, str):
        if cameras == "all":
            return list(range(scene.n_cameras))
        if cameras != "sparse":
            raise DatasetError(f"cameras must be 'sparse', 'all' or a list of indices, got {cameras!r}")
        if scene.n_cameras <= max(SPARSE_VIEW_CAMERAS):
            raise DatasetError(
                f"the sparse-view protocol uses camera indices {list(SPARSE_VIEW_CAMERAS)} (cameras "
                f"{list(SPARSE_VIEW_CAMERAS_ONE_BASED)} 1-based) but {scene.name} has "
                f"{scene.n_cameras} cameras (valid 0..{scene.n_cameras - 1}); pass cameras='all' "
                "or a list"
            )
        cameras = SPARSE_VIEW_CAMERAS
    out = [scene.check_camera(c) for c in cameras]
    if not out or len(set(out)) != len(out):
        raise DatasetError(f"cameras must be a non-empty list without repeats, got {list(cameras)}")
    return out


def _resize(t: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Area-resample a (H, W, C) tensor to ``size`` = (height, width)."""
    if tuple(t.shape[:2]) == size:
        return t
    return F.interpolate(t.permute(2, 0, 1)[None], size=size, mode="area")[0].permute(1, 2, 0)


class MultiViewDataset(Dataset):
    """Every (camera, frame) pair of a camera set and a frame set, loaded lazily.

    Item ``i`` is the pair ``(cameras[i % C], frames[i // C])`` (frame-major), a dict with
    ``image`` (H, W, 3) float32 in [0, 1], ``mask`` (H, W) float32 in [0, 1] (if ``masks``),
    ``cam`` and ``frame`` (int64 scalars, scene indices) and ``time`` (float32 scalar, seconds).
    Decoded (and resized) views are kept in an LRU cache bounded by ``cache_mb``.

    Args:
        scene: The scene.
        cameras: 0-based camera indices.
        frames: 0-based frame indices.
        downscale: Images are resized by ``1 / downscale`` (area averaging) to the size of
            ``scene.cameras.scaled(1 / downscale)``, exposed as :attr:`cameras`.
        cache_mb: Upper bound of the decoded-view cache in MiB (0 disables it).
        masks: Load masks too.
    """

    def __init__(
        self,
        scene: MultiViewScene,
        cameras: Sequence[int],
        frames: Sequence[int],
        *,
        downscale: float = 1.0,
        cache_mb: float = 512.0,
        masks: bool = True,
    ) -> None:
        self.scene = scene
        self.camera_indices = [scene.check_camera(c) for c in cameras]
        self.frame_indices = [scene.check_frame(f) for f in frames]
        if not (isinstance(downscale, (int, float)) and math.isfinite(downscale) and downscale > 0):
            raise ValueError(f"downscale must be a positive number, got {downscale!r}")
        self.cameras: Cameras = scene.cameras if downscale == 1 else scene.cameras.scaled(1.0 / downscale)
        self.size = (self.cameras.height, self.cameras.width)
        self.masks = masks
        self._cache: OrderedDict[tuple[int, int], tuple[torch.Tensor, torch.Tensor | None]] = OrderedDict()
        self._cache_bytes = 0
        self._cache_limit = int(cache_mb * 2**20)

    def __len__(self) -> int:
        return len(self.camera_indices) * len(self.frame_indices)

    def pair(self, index: int) -> tuple[int, int]:
        """``(camera, frame)`` scene indices of item ``index``."""
        if not 0 <= index < len(self):
            raise IndexError(f"item {index} out of range for {len(self)} views")
        n = len(self.camera_indices)
        return self.camera_indices[index % n], self.frame_indices[index // n]

    def _load(self, cam: int, frame: int) -> tuple[torch.Tensor, torch.Tensor | None]:
        key = (cam, frame)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        image = _resize(torch.from_numpy(self.scene.load_image(cam, frame)), self.size)
        mask = None
        if self.masks:
            mask = _resize(torch.from_numpy(self.scene.load_mask(cam, frame))[..., None], self.size)[..., 0]
        nbytes = image.nbytes + (mask.nbytes if mask is not None else 0)
        if nbytes <= self._cache_limit:
            self._cache[key] = (image, mask)
            self._cache_bytes += nbytes
            while self._cache_bytes > self._cache_limit:
                _, (old_i, old_m) = self._cache.popitem(last=False)
                self._cache_bytes -= old_i.nbytes + (old_m.nbytes if old_m is not None else 0)
        return image, mask

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        cam, frame = self.pair(index)
        image, mask = self._load(cam, frame)
        item = {
            "image": image,
            "cam": torch.tensor(cam, dtype=torch.int64),
            "frame": torch.tensor(frame, dtype=torch.int64),
            "time": torch.tensor(self.scene.times[frame], dtype=torch.float32),
        }
        if mask is not None:
            item["mask"] = mask
        return item


def collate_views(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack views into a batch: ``images`` (b, H, W, 3), ``masks`` (b, H, W), ``cam_indices``,
    ``frame_indices`` (b,) int64 and ``times`` (b,) float32."""
    batch = {
        "images": torch.stack([it["image"] for it in items]),
        "cam_indices": torch.stack([it["cam"] for it in items]),
        "frame_indices": torch.stack([it["frame"] for it in items]),
        "times": torch.stack([it["time"] for it in items]),
    }
    if all("mask" in it for it in items):
        batch["masks"] = torch.stack([it["mask"] for it in items])
    return batch


class CameraFrameBatchSampler(Sampler[list[int]]):
    """Batches of ``frames_per_batch`` frames x ``cameras_per_batch`` cameras of a
    :class:`MultiViewDataset`; every view appears exactly once per epoch.

    With ``shuffle``, frame and camera orders and the batch order are permuted with a generator
    seeded by ``seed + epoch``; the epoch advances by one after every pass (Lightning calls
    ``set_epoch`` only on samplers, not on batch samplers) and :meth:`set_epoch` sets it.
    """

    def __init__(
        self,
        n_cameras: int,
        n_frames: int,
        *,
        cameras_per_batch: int | None = None,
        frames_per_batch: int = 1,
        shuffle: bool = False,
        seed: int = 0,
    ) -> None:
        self.n_cameras, self.n_frames = n_cameras, n_frames
        self.cameras_per_batch = n_cameras if cameras_per_batch is None else cameras_per_batch
        self.frames_per_batch = frames_per_batch
        if self.cameras_per_batch < 1 or self.frames_per_batch < 1:
            raise ValueError("cameras_per_batch and frames_per_batch must be >= 1")
        self.shuffle, self.seed, self.epoch = shuffle, seed, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return math.ceil(self.n_frames / self.frames_per_batch) * math.ceil(self.n_cameras / self.cameras_per_batch)

    def __iter__(self) -> Iterator[list[int]]:
        gen = torch.Generator().manual_seed(self.seed + self.epoch)
        self.epoch += 1

        def order(n: int) -> list[int]:
            return torch.randperm(n, generator=gen).tolist() if self.shuffle else list(range(n))

        frames, cams = order(self.n_frames), order(self.n_cameras)
        fgroups = [frames[i : i + self.frames_per_batch] for i in range(0, self.n_frames, self.frames_per_batch)]
        cgroups = [cams[i : i + self.cameras_per_batch] for i in range(0, self.n_cameras, self.cameras_per_batch)]
        batches = [(fg, cg) for fg in fgroups for cg in cgroups]
        for b in order(len(batches)):
            fg, cg = batches[b]
            yield [f * self.n_cameras + c for f in fg for c in cg]


class MultiViewDataModule(pl.LightningDataModule):
    """Training, validation and evaluation views of one scene.

    * train: fitting cameras x frames ``[0, n_train)``, shuffled batches;
    * val: held-out cameras x all frames (fitting cameras x future frames when every camera
      fits; fitting cameras x training frames when there is no future either);
    * test: all cameras x all frames, the paper's evaluation (split metrics by ``n_train``).

    Args:
        scene: A :class:`MultiViewScene` or a scene folder (read with :func:`load_scene`).
        cameras: Fitting cameras: ``"sparse"`` (indices 1, 5, 9), ``"all"`` or 0-based indices.
        n_train: Number of fitting frames; None -> ``min(14, T)``.
        frames_per_batch: Frames per batch.
        cameras_per_batch: Cameras per batch (None: all fitting cameras of the split).
        downscale: Image downscale factor (cameras scaled to match, see :attr:`cameras`).
        cache_mb: Decoded-view cache bound per dataset, MiB.
        shuffle: Shuffle the training batches.
        seed: Seed of the training shuffle.
        num_workers: DataLoader workers.
        layout: Layout for a folder ``scene`` (``"auto"`` detects it).
    """

    def __init__(
        self,
        scene: MultiViewScene | str | Path,
        *,
        cameras: Sequence[int] | str = "sparse",
        n_train: int | None = None,
        frames_per_batch: int = 1,
        cameras_per_batch: int | None = None,
        downscale: float = 1.0,
        cache_mb: float = 512.0,
        shuffle: bool = True,
        seed: int = 0,
        num_workers: int = 0,
        layout: str = "auto",
    ) -> None:
        super().__init__()
        self.scene = scene if isinstance(scene, MultiViewScene) else load_scene(scene, layout)
        self.train_cameras = resolve_cameras(self.scene, cameras)
        self.held_out_cameras = [c for c in range(self.scene.n_cameras) if c not in self.train_cameras]
        n_frames = self.scene.n_frames
        if n_train is None:
            n_train = min(DEFAULT_N_TRAIN, n_frames)
        if not isinstance(n_train, (int, np.integer)) or not 1 <= n_train <= n_frames:
            raise DatasetError(f"n_train must be in 1..{n_frames} (the scene has {n_frames} frames), got {n_train!r}")
        self.n_train = int(n_train)
        self.train_frames = list(range(self.n_train))
        self.future_frames = list(range(self.n_train, n_frames))
        self.frames_per_batch = frames_per_batch
        self.cameras_per_batch = cameras_per_batch
        self.downscale = downscale
        self.cache_mb = cache_mb
        self.shuffle = shuffle
        self.seed = seed
        self.num_workers = num_workers
        self._datasets: dict[str, MultiViewDataset] = {}

    @property
    def cameras(self) -> Cameras:
        """All C cameras of the scene, scaled to the (downscaled) image size."""
        cams = self.scene.cameras
        return cams if self.downscale == 1 else cams.scaled(1.0 / self.downscale)

    def dataset(self, cameras: Sequence[int], frames: Sequence[int]) -> MultiViewDataset:
        """A dataset over any cameras x frames of the scene, with this module's settings."""
        return MultiViewDataset(
            self.scene, cameras, frames, downscale=self.downscale, cache_mb=self.cache_mb
        )

    def _split(self, name: str) -> MultiViewDataset:
        if name not in self._datasets:
            all_cams, all_frames = list(range(self.scene.n_cameras)), list(range(self.scene.n_frames))
            if name == "train":
                cams, frames = self.train_cameras, self.train_frames
            elif name == "val":
                if self.held_out_cameras:
                    cams, frames = self.held_out_cameras, all_frames
                else:
                    cams, frames = self.train_cameras, self.future_frames or self.train_frames
            else:
                cams, frames = all_cams, all_frames
            self._datasets[name] = self.dataset(cams, frames)
        return self._datasets[name]

    def setup(self, stage: str | None = None) -> None:
        """Datasets are cheap (lazy); they are built on first use."""

    def _loader(self, name: str, shuffle: bool) -> DataLoader:
        ds = self._split(name)
        per_cam = self.cameras_per_batch if name == "train" else None
        sampler = CameraFrameBatchSampler(
            len(ds.camera_indices), len(ds.frame_indices),
            cameras_per_batch=min(per_cam, len(ds.camera_indices)) if per_cam else None,
            frames_per_batch=self.frames_per_batch, shuffle=shuffle, seed=self.seed,
        )
        return DataLoader(
            ds, batch_sampler=sampler, collate_fn=collate_views, num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", self.shuffle)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", False)
