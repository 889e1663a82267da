"""Accuracy from default guesses on images the fitting renderer did not make (issue #20).

The scene is the project's generator's (tests/physics_fixtures.tiny_scene: an elastic box,
E = 3e4 Pa, nu = 0.3, thrown at v0 = (0.6, -0.8, 0.3) m/s; simulated with 4x the particles and
2.7x the substeps of the fit) and its images come from the truth renderer, a ray-cast textured and
shaded triangle mesh, not Gaussian splats. On top of that the images are altered the way real
footage differs from any renderer: a colour cast and gamma change of the lighting (object and
background plate alike) and salt-and-pepper noise on 1 % of the mask pixels. The whole pipeline
runs on it, stage 0 included, with nothing set but the material and CPU-sized schedules (default
guesses E = 10^5.5, nu = 0.25, default learning rates, coarse search on):
``projo4d run SCENE --material neo_hookean`` at tiny sizes.

Bounds (issue #20): E within 0.3 decades and v0 within 0.05 m/s (mean absolute error), asserted
at the fit's last iteration and on the reported estimate. Measured on CPU: the fit ends at
E 0.02 decades and v0 0.024 m/s from the truth. The reported estimate is the fit's for every
parameter the clip determines (the uncertainty's MAP prior step moves only the undetermined ones;
when it moved all of them it reported v0 0.117 m/s off).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.physics_fixtures import FIT_SIM, TRUTH, V0, tiny_scene

#: a CPU-sized stage 0 (the tiny preset, shortened)
STAGE0 = {"preset": "tiny", "iterations": 200, "warmup": 30, "densify_from": 30, "densify_until": 110, "densify_interval": 40,
          "position_lr_max_steps": 200, "deform_lr_max_steps": 200}
CURRICULUM = "XAS:15@3,XASM:30"


def perturb_images(scene: Path, seed: int = 0) -> None:
    """Colour cast + gamma on every RGB(A) image of ``scene/data`` and 1 % mask salt-and-pepper noise."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    cast = np.array([0.85, 0.9, 1.05])
    for path in sorted((scene / "data").glob("*.png")):
        a = np.asarray(Image.open(path)).copy()
        rgb = a[..., :3].astype(np.float64) / 255.0
        rgb = np.clip(cast * rgb ** 1.2, 0.0, 1.0)
        a[..., :3] = np.round(rgb * 255).astype(np.uint8)
        if a.shape[-1] == 4:
            flip = rng.random(a.shape[:2]) < 0.01
            a[..., 3] = np.where(flip, 255 - a[..., 3], a[..., 3])
        Image.fromarray(a).save(path)


@pytest.mark.slow
def test_default_guesses_recover_E_and_v0_on_a_differently_rendered_scene(tmp_path):
    from toolkit.pipeline import RunSettings, run_pipeline

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene(tmp_path / "gen"), scene)
    perturb_images(scene)
    out = tmp_path / "run"
    run_pipeline(RunSettings(scene=str(scene), out=str(out), material="neo_hookean", stage0=STAGE0, sim=FIT_SIM,
                             curriculum=CURRICULUM, device="cpu", downscale=1, checkpoint_every=0))
    est = json.loads((out / "physics" / "estimate.json").read_text())
    search = json.loads((out / "physics" / "material_search.json").read_text())
    assert search["start"]["E"] == pytest.approx(10**5.5, rel=1e-5)  # from the default guess
    # the fit's last iteration
    end = json.loads((out / "physics" / "history.json").read_text())[-1]
    assert abs(math.log10(end["param/E"]) - math.log10(TRUTH["E"])) < 0.3, (end, search["best"])
    assert sum(abs(end[f"v0/{c}"] - V0[i]) for i, c in enumerate("xyz")) / 3 < 0.05, end
    # what `projo4d run` reports: after the uncertainty's MAP prior step (toolkit.physics.uncertainty)
    log_err = abs(math.log10(est["params"]["E"]) - math.log10(TRUTH["E"]))
    v0_err = sum(abs(a - b) for a, b in zip(est["v0"], V0)) / 3
    assert log_err < 0.3, (est["params"], search["best"])
    assert v0_err < 0.05, (est["v0"], [end[f"v0/{c}"] for c in "xyz"])
