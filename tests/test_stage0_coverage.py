"""Stage 0 losing the object is caught by the masks' coverage, not by PSNR.

A model whose Gaussians left the views renders only the black background, which on a small
object still scores about 27 dB (seen on 11 of 30 full-size sliding-box scenes at 96 px). The
coverage of each mask by the rendered alpha names the lost frames."""

from __future__ import annotations

import math

import pytest
import torch

from renderers import get_renderer
from renderers.base import Gaussians
from tests.test_stage0 import _ring_cameras, _sphere_gaussians, _sphere_masks
from toolkit.scene.coverage import coverage_record, format_frames, lost_frames, lost_object_message, mask_coverage
from toolkit.scene.stage0 import TrainingViews


class _DriftingSphere:
    """Gaussians on a sphere that follow the true sphere for ``follow`` frames and then fly off
    by ``drift`` metres a frame (what a diverged deformation does), rendered by a real renderer."""

    def __init__(self, g: Gaussians, follow: int, drift: float):
        self.g, self.follow, self.drift, self.renderer = g, follow, drift, get_renderer("torch")

    def render(self, cameras, time: float):
        frame = round(time / 0.1)
        shift = torch.tensor([max(0, frame - self.follow + 1) * self.drift, 0.0, 0.0])
        g = Gaussians(means=self.g.means + shift, log_scales=self.g.log_scales, quats=self.g.quats,
                      opacity_logits=self.g.opacity_logits, colors=self.g.colors)
        return self.renderer(g, cameras)


def _views(n_frames: int = 5):
    centre, radius = (0.0, 0.3, 0.0), 0.1
    cams = _ring_cameras(centre, size=32)[[0, 5, 10]]
    mask = _sphere_masks(cams, centre, radius)
    masks = mask[None].expand(n_frames, -1, -1, -1).clone()
    masks[-1, 1] = 0.0  # an empty mask (object out of that view) is not a lost frame
    images = masks[..., None].expand(-1, -1, -1, -1, 3).contiguous()
    times = torch.arange(n_frames, dtype=torch.float32) * 0.1
    return TrainingViews(cams, images, masks, times, list(range(n_frames)), [0, 5, 10], None), centre, radius


def test_coverage_names_the_frames_where_the_gaussians_left_the_object():
    views, centre, radius = _views()
    g = _sphere_gaussians(1500, radius, centre)
    cov = mask_coverage(_DriftingSphere(g, follow=3, drift=0.5), views)
    assert cov.shape == (5, 3) and math.isnan(float(cov[4, 1]))
    assert float(cov[:3].min()) > 0.9  # on the body: the masks are covered
    assert float(torch.nan_to_num(cov[3:], nan=0.0).max()) < 0.05  # half a metre off per frame: nothing covered
    assert lost_frames(cov) == [3, 4]
    record = coverage_record(cov)
    assert record["lost_frames"] == [3, 4] and record["per_frame_min"][:3] == pytest.approx([float(c) for c in cov[:3].amin(1)], abs=1e-4)
    message = lost_object_message(record, "RUN/stage0/coverage.json")
    assert "lost the object in training frames 3-4 of 0-4" in message and "RUN/stage0/coverage.json" in message, message
    # a model that follows every frame loses none
    assert lost_frames(mask_coverage(_DriftingSphere(g, follow=10, drift=0.5), views)) == []


def test_frame_lists_read_as_ranges():
    assert format_frames([1, 2, 3, 7, 9, 10]) == "1-3, 7, 9-10" and format_frames([0]) == "0" and format_frames([]) == ""
