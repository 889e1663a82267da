"""Datasets: one in-memory scene description, readers for the public layouts, a Lightning
DataModule.

* :class:`MultiViewScene`, :class:`GroundTruth` (:mod:`toolkit.data.scene`);
* readers :func:`read_pac_nerf`, :func:`read_spring_gaus`, :func:`read_spring_gaus_real`,
  :func:`read_vid2sim_gso` and :func:`load_scene` (layout detection);
* :func:`read_ground_truth` / :func:`write_ground_truth` (``ground_truth.json``) and PLY points;
* :class:`MultiViewDataset` / :class:`MultiViewDataModule` (import from
  :mod:`toolkit.data.datamodule`; kept out of here so importing the readers stays light).

Every reader error is a :class:`DatasetError` (a ``ValueError``) naming the file.
"""

from toolkit.data.errors import DatasetError
from toolkit.data.ground_truth import read_ground_truth, write_ground_truth
from toolkit.data.layout import READERS, detect_layout, load_scene
from toolkit.data.pac_nerf import read_pac_nerf
from toolkit.data.ply import read_ply_points, write_ply_points
from toolkit.data.scene import GroundTruth, MultiViewScene
from toolkit.data.spring_gaus import read_spring_gaus, read_spring_gaus_real
from toolkit.data.vid2sim import read_vid2sim_gso

__all__ = [
    "READERS",
    "DatasetError",
    "GroundTruth",
    "MultiViewScene",
    "detect_layout",
    "load_scene",
    "read_ground_truth",
    "read_pac_nerf",
    "read_ply_points",
    "read_spring_gaus",
    "read_spring_gaus_real",
    "read_vid2sim_gso",
    "write_ground_truth",
    "write_ply_points",
]
