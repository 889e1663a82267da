"""Stage 0's data: every fitting view as tensors (:class:`TrainingViews`) and the Lightning data
module that feeds :class:`toolkit.scene.stage0.Gaussians4DModule` one step index per iteration."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator, Optional, Sequence

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, IterableDataset

from toolkit.cameras import Cameras

__all__ = ["TrainingViews", "Stage0DataModule"]


@dataclass
class TrainingViews:
    """All fitting views of a scene, as tensors (cached on the training device).

    Attributes:
        cameras: The C fitting cameras, scaled to the image size.
        images: (T, C, H, W, 3) float32 in [0, 1]; masked on black when masks exist.
        masks: (T, C, H, W) float32 object masks in [0, 1], or None.
        times: (T,) float32 frame times, seconds.
        frames: Scene frame index of each of the T frames.
        camera_indices: Scene camera index of each of the C cameras.
        keep: (C, H, W) float32 loss weights (0 = pixel excluded: PAC-NeRF frame -2 masks,
            :mod:`toolkit.data.exclusion`), or None.
        ground: ``(point, normal)`` of the dataset's ground plane in the cameras' frame (metres;
            the normal points into free space), or None when unknown.
    """

    cameras: Cameras
    images: torch.Tensor
    masks: Optional[torch.Tensor]
    times: torch.Tensor
    frames: list[int]
    camera_indices: list[int]
    keep: Optional[torch.Tensor] = None
    ground: Optional[tuple] = None

    @property
    def n_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def n_cameras(self) -> int:
        return int(self.images.shape[1])

    @property
    def device(self) -> torch.device:
        return self.images.device

    def to(self, device: torch.device | str) -> "TrainingViews":
        return TrainingViews(
            cameras=self.cameras.to(device),
            images=self.images.to(device),
            masks=None if self.masks is None else self.masks.to(device),
            times=self.times.to(device),
            frames=list(self.frames),
            camera_indices=list(self.camera_indices),
            keep=None if self.keep is None else self.keep.to(device),
            ground=self.ground,
        )

    @classmethod
    def from_datamodule(cls, dm: Any, composite_on_black: bool = True) -> "TrainingViews":
        """Load the training split (fitting cameras x training frames) of a
        :class:`toolkit.data.datamodule.MultiViewDataModule`."""
        cams_idx, frames = list(dm.train_cameras), list(dm.train_frames)
        ds = dm.dataset(cams_idx, frames)
        C, T = len(cams_idx), len(frames)
        imgs, masks = [], []
        has_masks = True
        for i in range(len(ds)):
            item = ds[i]
            imgs.append(item["image"])
            if "mask" in item:
                masks.append(item["mask"])
            else:
                has_masks = False
        H, W = imgs[0].shape[:2]
        images = torch.stack(imgs).reshape(T, C, H, W, 3).float()
        mask_t = torch.stack(masks).reshape(T, C, H, W).float() if has_masks and masks else None
        if mask_t is not None and composite_on_black:
            images = images * mask_t[..., None]
        times = torch.as_tensor(np.asarray(dm.scene.times)[frames], dtype=torch.float32)
        from toolkit.data.exclusion import keep_weights

        keep = keep_weights(dm.scene, cams_idx, size=(H, W))
        world = getattr(dm.scene, "world", None)
        ground = None if world is None else (tuple(world.ground_point), tuple(world.ground_normal))
        return cls(dm.cameras[cams_idx], images, mask_t, times, frames, cams_idx, keep, ground)


class _StepStream(IterableDataset):
    """Yields the module's iteration numbers from its current step to the end of the schedule."""

    def __init__(self, dm: "Stage0DataModule"):
        super().__init__()
        self.dm = dm

    def _range(self) -> range:
        module = self.dm.trainer.lightning_module if self.dm.trainer is not None else None
        if module is None:
            return range(0)
        stop = module.schedule.iterations if module.stop_at is None else min(module.stop_at, module.schedule.iterations)
        return range(module.step, max(module.step, stop))

    def __iter__(self) -> Iterator[int]:
        return iter(self._range())


class _StepLoader(DataLoader):
    """The step stream's loader. It is resumable by construction (the stream restarts at the
    module's restored step), which ``state_dict``/``load_state_dict`` tell Lightning."""

    def state_dict(self) -> dict:
        return {"resumes_at_module_step": True}

    def load_state_dict(self, state_dict: dict) -> None:
        pass


class Stage0DataModule(pl.LightningDataModule):
    """Training views for :class:`Gaussians4DModule`.

    The views (fitting cameras x training frames, see
    :class:`toolkit.data.datamodule.MultiViewDataModule`) are loaded once and cached on the
    training device by the module; the train dataloader only yields iteration numbers (the
    module picks the frame of each iteration), so no image is copied to the device per step.

    Args:
        scene: A :class:`MultiViewScene`, a scene folder, or None when ``views`` is given.
        cameras: Fitting cameras (``"sparse"``, ``"all"`` or 0-based indices).
        n_train: Number of training frames (None: min(14, T)).
        downscale: Image downscale factor.
        composite_on_black: Multiply images by their masks (ground truth on black).
        layout: Layout of a scene folder.
        views: Ready-made :class:`TrainingViews` (benchmarks, tests) instead of a scene.
    """

    def __init__(
        self,
        scene: Any = None,
        *,
        cameras: Sequence[int] | str = "sparse",
        n_train: Optional[int] = None,
        downscale: float = 1.0,
        composite_on_black: bool = True,
        layout: str = "auto",
        views: Optional[TrainingViews] = None,
    ) -> None:
        super().__init__()
        if (scene is None) == (views is None):
            raise ValueError("give exactly one of scene or views")
        self.multiview = None
        if scene is not None:
            from toolkit.data.datamodule import MultiViewDataModule

            self.multiview = MultiViewDataModule(
                scene, cameras=cameras, n_train=n_train, downscale=downscale, shuffle=False, layout=layout
            )
        self.composite_on_black = composite_on_black
        self._views = views

    def training_views(self) -> TrainingViews:
        """The training views on the CPU (loaded on first use)."""
        if self._views is None:
            self._views = TrainingViews.from_datamodule(self.multiview, self.composite_on_black)
        return self._views

    def train_dataloader(self) -> DataLoader:
        return _StepLoader(_StepStream(self), batch_size=None, num_workers=0)
