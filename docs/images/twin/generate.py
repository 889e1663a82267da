"""Regenerate the pictures of docs/tutorials/digital_twin.md (CPU, about a minute; needs chromium for the viewer shot).

    .venv/bin/python docs/images/twin/generate.py

Fits the tutorial's tiny scene (oracle geometry), exports the twin, re-simulates a new throw and writes
``viewer.png`` (the browser viewer in headless Chromium), ``static_view.png`` (``projo4d view``) and
``resimulated.png`` (fitted throw above, a new throw with a 10x stiffer material below, orbit camera).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2]))


def main() -> None:
    import imageio.v3 as iio

    from toolkit.pipeline import RunSettings, run_pipeline
    from toolkit.synthetic import SceneSpec, generate_scene
    from toolkit.twin import DigitalTwin, orbit_cameras, render_trajectory, simulate_twin
    from toolkit.twin.export import export_run
    from toolkit.viewer import write_views

    work = Path(tempfile.mkdtemp(prefix="twin_docs_"))
    spec = SceneSpec.preset("small", shape="box", shape_size={"size_x": 0.12, "size_y": 0.08, "size_z": 0.1},
                            params={"E": 3e4, "nu": 0.3}, v0=(0.6, -0.8, 0.3), position=(0.0, 0.16, 0.0), n_frames=6,
                            n_train_frames=5, width=32, height=32, dx=0.04, particle_spacing=0.01, substeps=80,
                            supersample=1, ground_plane=False)
    scene = generate_scene(spec, work / "scene", progress=False)
    run_pipeline(RunSettings(scene=str(scene), out=str(work / "run"), geometry="oracle", curriculum="XAS:4@3,XASM:4",
                             initial_params={"E": 1e4, "nu": 0.3}, optimize_params=["E"],
                             learning_rates={"velocity": 0.1, "E": 0.1}, sim={"dx": 0.04, "substeps": 30}, device="cpu"))
    files = export_run(work / "run")
    twin = DigitalTwin.load(files["twin"])
    cams = orbit_cameras(twin, n=1, width=160, height=120, elevation_deg=15)
    fitted = render_trajectory(twin, simulate_twin(twin, n_frames=8), cams)[:, 0]
    stiff = render_trajectory(twin, simulate_twin(twin, v0=[-0.3, 1.2, 0.0], params={"E": 10 * twin.params["E"]}, n_frames=8),
                              cams)[:, 0]
    rows = [np.concatenate(list(x[::2]), axis=1) for x in (fitted, stiff)]
    iio.imwrite(HERE / "resimulated.png", (np.concatenate(rows, axis=0) * 255).astype(np.uint8))
    write_views(work / "run", work / "view", frames=[5], formats=("png",), size=(800, 400))
    shutil.copy(work / "view" / "frame_005.png", HERE / "static_view.png")
    chromium = shutil.which("chromium")
    if chromium:
        from toolkit.twin.viewer import serve_run

        v = serve_run(work / "run", port=0, block=False)
        try:
            subprocess.run([chromium, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                            "--window-size=1100,620", "--virtual-time-budget=15000", f"--screenshot={HERE / 'viewer.png'}",
                            v.url], check=True, capture_output=True, timeout=120)
        finally:
            v.close()
    print("wrote", sorted(p.name for p in HERE.glob("*.png")))


if __name__ == "__main__":
    main()
