"""Bad input and failed rollouts give clear errors, never a hang or a crash."""

from __future__ import annotations

import math

import pytest
import torch

from materials import MaterialError, get_material
from tests.mpm_scenes import block
from toolkit.mpm import CFLError, MPMSimulator, NaNError, OutOfDomainError, SimConfig
from toolkit.mpm.effects import EffectError


def _sim(device, **cfg):
    base = dict(dx=0.05, substeps=20)
    base.update(cfg)
    return MPMSimulator("neo_hookean", SimConfig(**base), device=device)


def test_initial_particles_outside_domain(device):
    sim = _sim(device, domain=((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)))
    x0 = block((3, 3, 3), 0.02, (1.5, 0.2, 0.2))
    with pytest.raises(OutOfDomainError, match=r"outside the simulation domain.*particle 0") as info:
        sim.rollout(x0, n_frames=1)
    assert info.value.frame == 0


def test_particle_leaving_domain_names_frame(device):
    sim = _sim(device, domain=((0.0, -0.2, 0.0), (1.0, 1.0, 1.0)), ground_height=None, gravity=(0, 0, 0))
    x0 = block((3, 3, 3), 0.02, (0.5, 0.5, 0.5))
    with pytest.raises(OutOfDomainError, match=r"left the simulation domain .* at frame (\d+)") as info:
        sim.rollout(x0, torch.tensor([3.0, 0.0, 0.0]), sim.material.pack({"E": 1e4}), n_frames=8)
    # x reaches 1.0 - 1.5 dx = 0.925 m after ~0.13 s = frame 3
    assert info.value.frame == 3


def test_clamp_mode_keeps_particles_inside(device):
    sim = _sim(device, domain=((0.0, -0.2, 0.0), (1.0, 1.0, 1.0)), ground_height=None, gravity=(0, 0, 0),
               out_of_domain="clamp")
    x0 = block((3, 3, 3), 0.02, (0.5, 0.5, 0.5))
    out = sim.rollout(x0, torch.tensor([3.0, 0.0, 0.0]), sim.material.pack({"E": 1e4}), n_frames=8)
    # positions are clamped one cell inside the grid's last node (x = 1.0)
    assert out.positions[..., 0].max().item() <= 1.0 - 0.05 + 1e-5
    assert out.positions[..., 0].max().item() > 0.85  # they did reach the domain face (and bounced off it)
    assert torch.isfinite(out.positions).all()


@pytest.mark.parametrize("name,values,pattern", [
    ("neo_hookean", {"E": 0.0}, r"E = 0 is out of range: expected 0 < E"),
    ("neo_hookean", {"E": -5.0}, r"E = -5 is out of range"),
    ("neo_hookean", {"nu": 0.5}, r"nu = 0.5 is out of range: expected -0.99 <= nu <= 0.49"),
    ("newtonian", {"mu": -1.0}, r"mu = -1 is out of range"),
    ("sand", {"friction_angle": 95.0}, r"friction_angle = 95 is out of range"),
    ("plasticine", {"yield_stress": math.nan}, r"yield_stress must be a finite number"),
    ("plasticine", {"youngs": 1e5}, r"has no parameter\(s\) \['youngs'\]"),
])
def test_out_of_range_material_parameters(name, values, pattern):
    with pytest.raises(MaterialError, match=pattern):
        get_material(name).pack(values)


def test_bad_parameter_tensors_and_shapes(device):
    sim = _sim(device)
    x0 = block((3, 3, 3), 0.02, (0.5, 0.2, 0.5))
    with pytest.raises(MaterialError, match="NaN or inf"):
        sim.rollout(x0, None, torch.tensor([math.nan, 0.3]), n_frames=1)
    with pytest.raises(MaterialError, match="nu = 0.6"):
        sim.rollout(x0, None, torch.tensor([1e5, 0.6]), n_frames=1)
    with pytest.raises(ValueError, match=r"params for 'neo_hookean' must have shape .* with P = 2 \(E, nu\)"):
        sim.rollout(x0, None, torch.tensor([1e5, 0.3, 1.0]), n_frames=1)
    with pytest.raises(ValueError, match=r"x0 must have shape \(N, 3\)"):
        sim.rollout(x0[:, :2], n_frames=1)
    with pytest.raises(ValueError, match=r"v0 must have shape \(3,\) or \(N, 3\)"):
        sim.rollout(x0, torch.zeros(4), n_frames=1)
    with pytest.raises(ValueError, match="x0 contains NaN"):
        bad = x0.clone()
        bad[3, 1] = math.nan
        sim.rollout(bad, n_frames=1)
    with pytest.raises(ValueError, match=r"gravity must have shape \(3,\)"):
        sim.rollout(x0, gravity=torch.zeros(2), n_frames=1)
    with pytest.raises(ValueError, match="effect_params must have 0 values"):
        sim.rollout(x0, effect_params=torch.zeros(2), n_frames=1)
    with pytest.raises(ValueError, match="n_frames must be an integer"):
        sim.rollout(x0, n_frames=-1)


def test_cfl_violation_reports_frame_and_substep(device):
    # auto_substeps off: the configured 4 substeps are too few for 4 m/s at dx = 0.05
    sim = _sim(device, substeps=4, ground_height=None, margin=3.0, auto_substeps=False)
    x0 = block((3, 3, 3), 0.02, (0.5, 0.5, 0.5))
    with pytest.raises(CFLError, match=r"CFL violation at frame 0 \(substep 0 of 4") as info:
        sim.rollout(x0, torch.tensor([4.0, 0.0, 0.0]), sim.material.pack({"E": 1e3}), n_frames=2)
    # the real speed (4 m/s, no gravity) and a count that is stable: 4 m/s * dt <= 0.4 * 0.05 m needs >= 9
    msg = str(info.value)
    assert "up to 4 m/s" in msg and "limit 1.92 m/s at 4 substeps" in msg
    stable = int(msg.split("about ")[1].split(" substeps")[0])
    assert stable >= 9


def test_cfl_message_reports_the_real_speed_of_a_fast_body(device):
    """With v0 = 100 m/s the message used to say 'max speed 0 m/s' (the state after the failure)."""
    sim = _sim(device, substeps=10, margin=0.5, auto_substeps=False)
    x0 = block((3, 3, 3), 0.02, (0.5, 0.3, 0.5))
    with pytest.raises(CFLError) as info:
        sim.rollout(x0, torch.tensor([100.0, 0.0, 0.0]), sim.material.pack({"E": 1e4}), n_frames=1)
    msg = str(info.value)
    speed = float(msg.split("up to ")[1].split(" m/s")[0])
    assert 99.0 <= speed <= 101.0, msg  # 100 m/s and at most one substep of gravity
    stable = int(msg.split("about ")[1].split(" substeps")[0])
    assert stable >= 100.0 / 24.0 / (0.4 * 0.05)  # >= 209 substeps keep 100 m/s under 0.4 dx per substep
    # ... and the planner (auto_substeps, the default) gives a count that runs
    ok = _sim(device, substeps=10, margin=0.5)
    out = ok.rollout(x0, torch.tensor([100.0, 0.0, 0.0]), ok.material.pack({"E": 1e4}), n_frames=1)
    assert out.substeps >= 209 and ok.last_plan.reason == "speed"
    assert out.positions[-1, :, 0].mean().item() == pytest.approx(x0[:, 0].mean().item() + 100.0 / 24.0, abs=1e-3)


def test_auto_dt_halving_recovers(device):
    sim = _sim(device, substeps=4, ground_height=None, margin=3.0, auto_dt_halving=True, max_dt_halvings=3,
               auto_substeps=False)
    x0 = block((3, 3, 3), 0.02, (0.5, 0.5, 0.5))
    out = sim.rollout(x0, torch.tensor([4.0, 0.0, 0.0]), sim.material.pack({"E": 1e3}), n_frames=2)
    assert out.substeps == 16  # 4 m/s * dt <= 0.4 * 0.05 m needs dt <= 5 ms: 4 -> 8 -> 16 substeps
    assert torch.isfinite(out.positions).all()


def test_blow_up_is_reported_not_hung(device):
    sim = _sim(device, substeps=2, auto_substeps=False)
    x0 = block((4, 4, 4), 0.025, (0.5, 0.05, 0.5))
    with pytest.raises((NaNError, CFLError), match=r"at frame \d+"):
        sim.rollout(x0, torch.tensor([0.0, -1.0, 0.0]), sim.material.pack({"E": 1e9, "nu": 0.3}), n_frames=5)


def test_bad_config_and_effects():
    with pytest.raises(ValueError, match="SimConfig: dx must be a positive length"):
        SimConfig(dx=0.0)
    with pytest.raises(ValueError, match=r"SimConfig: boundary must be one of \('sticky', 'slip', 'separate'\)"):
        SimConfig(boundary="bouncy")
    with pytest.raises(ValueError, match="substeps must be an integer >= 1"):
        SimConfig(substeps=0)
    with pytest.raises(KeyError, match=r"unknown effect 'air_drg'. Did you mean 'air_drag'\?"):
        MPMSimulator("neo_hookean", effects=["air_drg"])
    sim = MPMSimulator("neo_hookean", SimConfig(), effects=["air_drag"])
    with pytest.raises(EffectError, match=r"air_drag.linear = -1 is out of range"):
        sim.pack_effects({"air_drag": {"linear": -1.0}})
    with pytest.raises(ValueError, match=r"no effect\(s\) \['wall'\] in this simulator"):
        sim.pack_effects({"wall": {"strength": 1.0}})
    with pytest.raises(EffectError, match="wall normal must be a non-zero 3-vector"):
        from toolkit.mpm.effects import get_effect

        get_effect("wall", normal=(0, 0, 0))
    with pytest.raises(EffectError, match="ground_friction needs a ground plane"):
        s = MPMSimulator("neo_hookean", SimConfig(ground_height=None), effects=["ground_friction"])
        s.rollout(block((2, 2, 2), 0.02, (0.5, 0.5, 0.5)), n_frames=1)


def test_auto_sized_grid_grows_and_gives_the_big_grid_result(device):
    """An extra acceleration (not known to the grid's ballistic estimate) turns the body back past
    its start and out of the auto-sized grid: the grid grows and the rollout is rerun; the result
    equals a rollout on a grid that was large enough from the start."""
    x0 = block((4, 4, 4), 0.02, (0.5, 0.5, 0.5))
    v0 = torch.tensor([3.0, 0.0, 0.0])
    kw = dict(dx=0.04, substeps=40, ground_height=None, gravity=(0.0, 0.0, 0.0))

    def run(**cfg):
        sim = MPMSimulator("neo_hookean", SimConfig(**kw, **cfg), effects=["extra_acceleration"], device=device)
        ep = sim.pack_effects({"extra_acceleration": {"ax": -20.0}})
        return sim, sim.rollout(x0, v0, sim.material.pack({"E": 2e4}), effect_params=ep, n_frames=12)

    small, out = run(margin=0.05)
    assert small.grid.origin[0] < -0.4  # x reaches 0.5 + 3 t - 10 t^2 = -0.5 m at t = 0.5 s: the grid grew
    assert out.positions[..., 0].min().item() < -0.4
    _, ref = run(domain=((-1.2, 0.0, 0.0), (1.6, 1.0, 1.0)))
    torch.testing.assert_close(out.positions, ref.positions, atol=1e-5, rtol=0)
    with pytest.raises(OutOfDomainError, match="left the simulation domain"):
        run(margin=0.05, out_of_domain="error")
