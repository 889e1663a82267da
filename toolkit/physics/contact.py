"""Ground contact at frame 0: which initial velocities the clip can see at all.

A body that starts resting on a non-separating ground (boundary ``sticky`` or ``slip``) cannot have
an initial velocity along the ground normal: the grid update removes the normal velocity of every
ground node in the first substep, so any value the fit gives it is unconstrained by the video
(issue #24 measured v0_y = +0.62 m/s for a puck sliding on the ground). The fit therefore keeps the
normal component of v0 at zero for such a body (:func:`project_off_ground`).

Conventions: the simulator's ground is the plane ``y = SimConfig.ground_height`` with normal +y in
the canonical world (DESIGN section 4); positions in metres, velocities in m/s.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch

__all__ = ["GROUND_NORMAL", "CONTACT_CELLS", "CONTACT_FRAMES", "NON_SEPARATING", "ground_contact_normal", "project_off_ground"]

#: the simulator's ground normal (canonical world)
GROUND_NORMAL = (0.0, 1.0, 0.0)
#: a body whose lowest particle is within this many grid cells (``dx``) of the ground starts in contact
CONTACT_CELLS = 1.0
#: observed frames (from frame 0) in which the body must stay within that band to count as resting
CONTACT_FRAMES = 3
#: boundary modes that remove the normal velocity of ground nodes in both directions
NON_SEPARATING = ("sticky", "slip")


def ground_contact_normal(particles: torch.Tensor, sim_config, surfaces: Optional[Sequence[torch.Tensor]] = None,
                          frames: int = CONTACT_FRAMES) -> Optional[tuple[float, float, float]]:
    """The ground normal if the body rests on a non-separating ground at frame 0, else ``None``.

    Args:
        particles: (N, 3) initial particle positions, metres (canonical world, y up).
        sim_config: a :class:`~toolkit.mpm.SimConfig` (uses ``ground_height``, ``boundary``, ``dx``).
        surfaces: the observed surfaces per frame ((M_t, 3) each, metres); when given, the body must
            also stay within the contact band in the first ``frames`` of them (a lob that starts on
            the ground and takes off is not held down).
        frames: frames of ``surfaces`` checked (frame 0 included).

    Returns:
        ``GROUND_NORMAL`` when ``ground_height`` is set, ``boundary`` is ``sticky`` or ``slip`` and
        the lowest point is within ``CONTACT_CELLS * dx`` of the ground (at frame 0 and in the
        checked surfaces); otherwise ``None``.
    """
    ground = getattr(sim_config, "ground_height", None)
    if ground is None or getattr(sim_config, "boundary", "sticky") not in NON_SEPARATING or len(particles) == 0:
        return None
    band = float(ground) + CONTACT_CELLS * float(sim_config.dx)
    lowest = [float(particles[:, 1].min())]
    lowest += [float(s[:, 1].min()) for s in list(surfaces or [])[:frames] if len(s)]
    return GROUND_NORMAL if max(lowest) <= band else None


@torch.no_grad()
def project_off_ground(v0: torch.Tensor, normal: Optional[tuple[float, float, float]]) -> torch.Tensor:
    """Remove the component of ``v0`` (3,) along ``normal`` in place (nothing when ``normal`` is None)."""
    if normal is not None:
        n = torch.tensor(normal, dtype=v0.dtype, device=v0.device)
        v0.sub_((v0 @ n) * n)
    return v0
