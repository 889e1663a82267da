"""What one iteration of the inverse-physics fit minimizes, as a mixin of
:class:`~toolkit.physics.module.InversePhysicsModule`: the rollout from the current state, the
Gaussians it carries (means, and shapes when they deform) and the loss terms

    lambda_img * sum_cameras L_img + lambda_geo * chamfer(simulated surface, stage-0 surface),

averaged over the sampled frames, with ``L_img = (1 - w) L1 + w (1 - SSIM)`` on the masked image.
"""

from __future__ import annotations

import contextlib
import logging
from typing import Optional, Sequence

import torch

from renderers import Gaussians
from toolkit.data.exclusion import apply_keep
from toolkit.metrics.geometry import chamfer_loss
from toolkit.metrics.image import ssim_torch
from toolkit.physics.embedding import carry, carry_deformation

__all__ = ["FitObjectiveMixin"]

log = logging.getLogger("toolkit.physics.module")


class FitObjectiveMixin:
    """Rollout, carried Gaussians and loss terms of the fit (needs the module's buffers and parameters)."""

    def carried(self, positions: torch.Tensor, x0: torch.Tensor) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """Gaussian means (F, G, 3) and deformations (F, G, 3, 3), or None for rigid shapes, at
        the frames of ``positions`` (F, N, 3) simulated from ``x0`` (N, 3)."""
        means = carry(self.gaussian_means0 + self.gaussian_offset, positions, x0, self.embed_index, self.embed_weight)
        if not self.deform_index.numel():
            return means, None
        return means, carry_deformation(positions, x0, self.deform_index, self.deform_gradient)

    def gaussians_at(self, positions: torch.Tensor, x0: torch.Tensor, appearance_grad: bool = True) -> list[Gaussians]:
        """Gaussians for each frame of ``positions`` (F, N, 3) simulated from ``x0``."""
        means, deformations = self.carried(positions, x0)
        A = (lambda t: t) if appearance_grad else (lambda t: None if t is None else t.detach())  # noqa: E731
        return [Gaussians(means=m, log_scales=A(self.log_scales), quats=A(self.quats), opacity_logits=A(self.opacity_logits),
                          colors=A(self.colors), sh=A(self.sh), deformation=None if deformations is None else deformations[i])
                for i, m in enumerate(means)]

    def simulate(self, n_frames: int, groups: frozenset = frozenset("XSM")):
        """Simulate ``n_frames`` frames from the current state; gradients only for ``groups``."""
        x0 = self.particles0 + (self.particle_offset if "X" in groups else self.particle_offset.detach())
        v0 = self.v0 if "S" in groups else self.v0.detach()
        gravity = self.gravity if ("S" in groups and self.optimize_gravity) else self.gravity.detach()
        params = self.material_params() if "M" in groups else self.material_params().detach()
        effects = self.effect_params if "M" in groups else self.effect_params.detach()
        # the simulator re-plans the substeps from these parameters (a stiffer material gets more)
        out = self.simulator.simulate(x0, v0, params, gravity=gravity, effect_params=effects, n_frames=n_frames)
        self._note_substeps(out.substeps)
        return x0, out.positions

    @contextlib.contextmanager
    def substeps_unlogged(self):
        """Rollouts inside neither log nor record substep changes (probes around the estimate, such
        as the uncertainty's perturbed parameters, are not steps of the fit)."""
        previous, self._log_substeps = getattr(self, "_log_substeps", True), False
        try:
            yield
        finally:
            self._log_substeps = previous

    def _note_substeps(self, substeps: int) -> None:
        """Log a line when the substeps per frame change (a re-plan or a dt halving)."""
        if not getattr(self, "_log_substeps", True):
            return
        if substeps != self.substeps:
            plan = self.simulator.last_plan
            why = "" if plan is None else (
                f" ({'dt halving' if substeps > plan.substeps else plan.reason}: wave speed {plan.wave_speed:.3g} m/s, "
                f"initial speed {plan.max_speed:.3g} m/s, configured {plan.configured})")
            if self.substeps is None:
                log.info("simulating with %d substeps per frame%s", substeps, why)
            else:
                log.info("substeps per frame %d -> %d at iteration %d%s", self.substeps, substeps, self.curriculum_step, why)
            self.substeps = int(substeps)

    def losses(self, stage, cams: Sequence[int], frames: Sequence[int]) -> dict[str, torch.Tensor]:
        """Loss terms of one iteration (differentiable with respect to the stage's groups)."""
        groups = stage.groups
        n_sim = max(frames)
        if groups & {"X", "S", "M"} or self._cached_positions is None or self._cached_positions[1].shape[0] <= n_sim:
            x0, positions = self.simulate(max(n_sim, 0), groups)
            if not groups & {"X", "S", "M"}:
                self._cached_positions = (x0.detach(), positions.detach())
        else:
            x0, positions = self._cached_positions
        out: dict[str, torch.Tensor] = {}
        zero = torch.zeros((), device=positions.device)
        total = zero
        if "image" in stage.losses:
            gauss = self.gaussians_at(positions[frames], x0, appearance_grad="A" in groups)
            if "X" not in groups:
                gauss = [g.replace(means=g.means.detach()) if not (groups & {"S", "M"}) else g for g in gauss]
            cam_batch = self.input.cameras[cams].to(positions.device)
            img_loss = zero
            for f, g in zip(frames, gauss):
                render = self.renderer(g, cam_batch)
                gt = self.images[cams, f].float() / 255.0
                mask = self.masks[cams, f].float().unsqueeze(-1) / 255.0
                gt = gt * mask
                keep = self.exclusion_keep[cams].float() / 255.0 if self.exclusion_keep.numel() else None
                rgb, gt = apply_keep(render.rgb, gt, keep)
                l1 = (rgb - gt).abs().mean(dim=(1, 2, 3))
                ssim = ssim_torch(rgb, gt, reduction="none").reshape(len(cams), -1).mean(1)
                per_cam = (1 - self.ssim_weight) * l1 + self.ssim_weight * (1 - ssim)
                img_loss = img_loss + self.lambda_image * per_cam.sum()
            out["image"] = img_loss / len(frames)
            total = total + out["image"]
        if "geometry" in stage.losses and self.lambda_geometry > 0:
            geo = zero
            for f in frames:
                target = self.input.surfaces[f].to(positions.device)
                if len(target):
                    geo = geo + chamfer_loss(positions[f][self.surface_index], target)
            out["geometry"] = self.lambda_geometry * geo / len(frames)
            total = total + out["geometry"]
        out["total"] = total
        return out
