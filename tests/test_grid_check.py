"""The grid check (toolkit.physics.grid_check): the same state on a grid of half the spacing.

Physics: free flight is exactly ballistic on any grid (the check reads ~0); an impact of a body
two cells thick is not resolved (the check reads millimetres); children of a split particle keep
its centre and sit on the half-pitch lattice."""

from __future__ import annotations

import torch

from tests.mpm_scenes import block
from toolkit.mpm import MPMSimulator, SimConfig
from toolkit.physics.grid_check import (
    GRID_NOTE,
    annotate_grid,
    format_grid_check,
    grid_shift,
    subdivide,
)


def test_subdivide_keeps_the_centre_on_the_half_pitch_lattice():
    x = block((3, 2, 2), 0.02, (0.1, 0.2, 0.3))
    kids = subdivide(x, 0.02)
    assert kids.shape == (8 * x.shape[0], 3)
    torch.testing.assert_close(kids.reshape(-1, 8, 3).mean(1), x)
    fine = block((6, 4, 4), 0.01, (0.1, 0.2, 0.3))  # the lattice of half the pitch over the same box
    torch.testing.assert_close(torch.unique(kids.round(decimals=5), dim=0), torch.unique(fine.round(decimals=5), dim=0))


def _sim(dx: float) -> MPMSimulator:
    return MPMSimulator("neo_hookean", SimConfig(dx=dx, substeps=40, particle_volume=(dx / 2) ** 3, auto_dt_halving=True),
                        device="cpu")


def test_free_flight_moves_only_by_the_time_step():
    """Free flight is exactly ballistic on any grid; what changes with the finer grid's smaller
    time step is symplectic Euler's drift, x(t) = x0 + v0 t + g t^2 / 2 + g t dt / 2, so the shift
    of frame f is |g| t_f (dt_coarse - dt_fine) / 2."""
    sim = _sim(0.04)
    x0 = block((4, 4, 4), 0.02, (0.3, 0.8, 0.3))  # far above the ground for 4 frames
    params = sim.material.pack({"E": 1e5, "nu": 0.3})
    rec = grid_shift(sim, x0, torch.tensor([0.5, 0.5, -0.2]), params, torch.tensor([0.0, -9.8, 0.0]),
                     torch.zeros(0), n_frames=4)
    assert (rec["dx"], rec["fine_dx"]) == (0.04, 0.02) and rec["fine_substeps"] > rec["substeps"]
    frame_dt = sim.config.frame_dt
    dt_c, dt_f = frame_dt / rec["substeps"], frame_dt / rec["fine_substeps"]
    expected = [9.8 * f * frame_dt * (dt_c - dt_f) / 2 for f in range(5)]
    torch.testing.assert_close(torch.tensor(rec["shift_per_frame_m"]), torch.tensor(expected), rtol=0.02, atol=2e-6)


def test_an_unresolved_impact_moves_with_the_grid():
    """A stiff slab two cells thick thrown onto the sticky ground: the coarse grid cannot bend it
    as the fine one does, and the check reads millimetres (ten times the free flight's drift)."""
    sim = _sim(0.04)
    x0 = block((8, 4, 8), 0.02, (0.3, 0.05, 0.3))
    params = sim.material.pack({"E": 3e5, "nu": 0.3})
    rec = grid_shift(sim, x0, torch.tensor([0.6, -1.5, 0.0]), params, torch.tensor([0.0, -9.8, 0.0]),
                     torch.zeros(0), n_frames=5)
    assert rec["shift_m"] > 2e-3, rec
    assert rec["shift_per_frame_m"][0] < 1e-6 and max(rec["shift_per_frame_m"]) > rec["shift_m"]
    line = format_grid_check({**rec, "residual_m": 1e-3, "ratio": rec["shift_m"] / 1e-3, "converged": False})
    assert "fit again with --sim '{\"dx\": 0.02}'" in line
    # a shift below a large misfit is not called resolved: the line gives the misfit and its floor
    # (round 4's letter T: a 47 mm shift under a 68 mm residual)
    missed = format_grid_check({**rec, "shift_m": 0.047, "residual_m": 0.068, "first_frame_residual_m": 0.003,
                                "ratio": 0.047 / 0.068, "converged": True})
    assert "0.7x the fit's residual (68.00 mm; 3.00 mm at the first frame" in missed
    assert "less than the fit misses the data" in missed and "resolves" not in missed


def test_a_failed_check_marks_the_material_parameters_only():
    rows = [{"parameter": "E", "note": ""}, {"parameter": "nu", "note": "weakly determined"}, {"parameter": "v0_x", "note": ""}]
    annotate_grid(rows, {"converged": True}, ["E", "nu"])
    assert [r["note"] for r in rows] == ["", "weakly determined", ""]
    annotate_grid(rows, {"converged": False}, ["E", "nu"])
    assert [r["note"] for r in rows] == [GRID_NOTE, f"weakly determined; {GRID_NOTE}", ""]
    annotate_grid(rows, {"skipped": "GridTooLargeError: ..."}, ["E"])  # no verdict: nothing added
    assert rows[0]["note"] == GRID_NOTE
