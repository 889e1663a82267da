"""Discovery's library model keeps v0's normal component at zero for a body resting on the ground.

The scene is the uncertainty tests' frictionless slide (:func:`tests.uncertainty_scenes.slide_scene`):
a box whose lowest point is 2 cm above a slip ground at frame 0 (within one fitting cell, 4 cm) and
which stays there, sliding sideways. The module holds v0's normal component at zero for such a body
(issue #24, :mod:`toolkit.physics.contact`); the library must do the same, or its refits move a
component the video cannot see and the exported config replays another motion.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tests.uncertainty_scenes import slide_input, slide_module_at_truth, slide_sim

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def slide_library(tmp_path_factory):
    from toolkit.discovery.library import LibraryModel

    module = slide_module_at_truth(slide_input(tmp_path_factory.mktemp("slide")))
    return LibraryModel(module, candidates=["ground_friction", "air_drag", "extra_acceleration"])


def test_a_resting_body_keeps_no_initial_velocity_into_the_ground(slide_library):
    """The library reads the module's contact normal, holds ``v0.y`` (group ``held``, never
    refitted) and its forward model drops a value a caller writes there; a push along the ground
    does move the body (so the comparison can fail)."""
    lib = slide_library
    assert lib.module.contact_normal == (0.0, 1.0, 0.0)
    assert lib.contact_normal == (0.0, 1.0, 0.0)
    assert "v0.y" not in lib.base_names and "v0.x" in lib.base_names and lib.params_of("held") == ["v0.y"]
    q = lib.q0.copy()
    assert q[lib.index_of["v0.y"]] == 0.0
    pushed = q.copy()
    pushed[lib.index_of["v0.y"]] = -0.5
    assert lib.physical(pushed)["v0"][1] == 0.0
    _, a = lib.trajectory(q, [1, 3])
    _, b = lib.trajectory(pushed, [1, 3])
    assert torch.equal(a, b)
    sideways = q.copy()
    sideways[lib.index_of["v0.x"]] += 0.5
    _, c = lib.trajectory(sideways, [1, 3])
    assert float((c - a).abs().max()) > 0.01


def test_on_a_ground_it_may_leave_every_component_of_v0_is_refitted(slide_library):
    """The same slide over a ``separate`` ground (a body may lift off it, so an upward v0 is seen):
    no contact normal, all three components of v0 are refitted, and a push along the normal
    changes the motion."""
    from toolkit.discovery.library import LibraryModel

    module = slide_module_at_truth(slide_library.input, dataclasses.replace(slide_sim(), boundary="separate"))
    lib = LibraryModel(module, candidates=["ground_friction"])
    assert module.contact_normal is None and lib.contact_normal is None
    assert {"v0.x", "v0.y", "v0.z"} <= set(lib.base_names) and lib.params_of("held") == []
    q = lib.q0.copy()
    pushed = q.copy()
    pushed[lib.index_of["v0.y"]] = 0.5
    assert lib.physical(pushed)["v0"][1] == pytest.approx(0.5)
    _, a = lib.trajectory(q, [1, 3])
    _, b = lib.trajectory(pushed, [1, 3])
    assert float((b - a).abs().max()) > 0.01
