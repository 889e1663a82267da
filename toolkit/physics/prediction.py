"""What a fitted :class:`~toolkit.physics.InversePhysicsModule` predicts and how far it is from
the truth: the whole trajectory, renders of it, and parameter errors (a mixin of the module)."""

from __future__ import annotations

from typing import Optional, Sequence

import torch

from renderers import Gaussians

__all__ = ["PredictionMixin"]


class PredictionMixin:
    """Prediction and evaluation methods; they use the module's input, simulator, Gaussians and
    renderer (``self.input``, ``self.simulate``, ``self.gaussian_*``, ``self.renderer``, ...)."""

    def probe_losses(self, positions: torch.Tensor, stage, cams: Sequence[int], frames: Sequence[int]) -> dict[str, float]:
        """The fit's loss terms (:meth:`losses` of ``stage``: image and geometric) for simulated
        ``positions`` ((T+1, N, 3), m, frame 0 first, covering ``max(frames)``) instead of the
        module's own rollout; no gradients, nothing of the module changed. Used to score states the
        fit is not in (the coarse search's candidates, the uncertainty's probes)."""
        import dataclasses

        probe = dataclasses.replace(stage, groups=frozenset())
        x0 = (self.particles0 + self.particle_offset).detach()
        self._cached_positions = (x0, positions)
        try:
            with torch.no_grad():
                return {k: float(v) for k, v in self.losses(probe, cams, frames).items()}
        finally:
            self._cached_positions = None

    def parameter_errors(self, est: dict | None = None) -> dict[str, float]:
        """Errors against the ground truth when it is known (for logging; never used by the fit)."""
        gt = self._ground_truth
        if not gt or not gt.get("params"):
            return {}
        from toolkit.metrics.parameters import parameter_errors

        est = est or self.estimate()
        pred = dict(est["params"])
        truth = dict(gt["params"])
        if gt.get("v0") is not None:
            pred["v0"], truth["v0"] = est["v0"], gt["v0"]
        errs = parameter_errors(pred, truth)
        return {f"error/{k}": float(v) for k, v in errs.items() if isinstance(v, (int, float))}

    @torch.no_grad()
    def predict_trajectory(self, n_frames: Optional[int] = None) -> dict[str, torch.Tensor]:
        """Simulate all frames (training and future) with the current estimate.

        Returns:
            ``positions`` (T, N, 3) particle positions and ``means`` (T, G, 3) Gaussian means, metres;
            with deformed Gaussian shapes also ``deformations`` (T, G, 3, 3).
        """
        n_frames = n_frames or self.input.n_frames
        x0, positions = self.simulate(n_frames - 1, frozenset())
        means, deformations = self.carried(positions, x0)
        out = {"positions": positions, "means": means}
        if deformations is not None:
            out["deformations"] = deformations
        return out

    @torch.no_grad()
    def render_frames(self, means: torch.Tensor, cameras: Sequence[int],
                      deformations: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(T, C, H, W, 3) renders of the Gaussians at ``means`` (T, G, 3), shaped by
        ``deformations`` (T, G, 3, 3) when given, for ``cameras``."""
        cams = self.input.cameras[list(cameras)].to(means.device)
        out = []
        for t, m in enumerate(means):
            g = Gaussians(means=m, log_scales=self.log_scales, quats=self.quats, opacity_logits=self.opacity_logits,
                          colors=self.colors, sh=self.sh, deformation=None if deformations is None else deformations[t])
            out.append(self.renderer(g, cams).rgb.clamp(0, 1))
        return torch.stack(out)
