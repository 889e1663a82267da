"""The silhouette check (``toolkit.scene.silhouette_agreement``) on the discovery suite's scenes.

Generates the discovery benchmark's scenes (``toolkit.discovery.hidden.hidden_suite``: every hidden
effect at both levels and the null scenes; ``--size full`` is 96 px with 3 of 10 cameras fitted)
and checks the fitting cameras' masks over the training frames with the cameras as a user would
have them: the true ones, except in the camera-pose scenes, whose perturbed fitted camera's centre
is moved by the hidden shift (1 cm medium, 2.5 cm high), as
:func:`toolkit.discovery.from_images.observed_scene` does. A camera named in any other scene is a
false alarm (no force changes the masks' agreement); in a camera-pose scene the moved camera
should be named. One JSON line per scene, then a summary line::

    python benchmarks/silhouette_check.py --out D                     # D/scenes is reused when present
    python benchmarks/silhouette_check.py --null 4 --size tiny --out D
    python benchmarks/silhouette_check.py --out D --variants D/scenes/none-none-neo_hookean-slide-s0

``--variants SCENE...`` checks instead the image variants of :data:`VARIANTS`
(``toolkit.synthetic.variants``: another renderer, mask noise, a photometric change, calibration
errors of every camera) of the given scenes, written to ``OUT/variants``.

Benchmarks are never part of the test suite.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

#: name -> VariantSpec fields of the checked image variants
VARIANTS = {"points": {"render_style": "points"}, "mask_noise_0.2": {"mask_noise": 0.2}, "mask_noise_0.5": {"mask_noise": 0.5},
            "photometric": {"gamma": 1.3, "blur_px": 1.0, "noise_std": 0.03}, "calib_0.5deg": {"calibration_deg": 0.5},
            "calib_1cm": {"calibration_m": 0.01}, "calib_2.5cm": {"calibration_m": 0.025}}


def check_variants(scenes: list[pathlib.Path], out: pathlib.Path) -> None:
    """One JSON line per scene and variant of :data:`VARIANTS` (the variants are written once)."""
    from toolkit.data.layout import load_scene
    from toolkit.pipeline import training_frames
    from toolkit.scene.silhouette_agreement import check_scene
    from toolkit.synthetic.variants import VariantSpec, make_variant

    for src in scenes:
        for name, fields in VARIANTS.items():
            dst = out / "variants" / f"{src.name}-{name}"
            if not (dst / "variant.json").is_file():
                make_variant(src, dst, VariantSpec(**fields))
            scene = load_scene(dst)
            check = check_scene(scene, "sparse", range(training_frames(scene, None)))
            print(json.dumps({"benchmark": "silhouette_check", "variant": name, "scene": src.name, **fields,
                              **check.to_dict()}), flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--null", type=int, default=20, help="null scenes (default 20, the discovery suite's)")
    p.add_argument("--size", default="full", choices=["tiny", "full"])
    p.add_argument("--out", type=pathlib.Path, required=True, help="folder for the generated scenes")
    p.add_argument("--shard", default="0/1", help="I/N: this process checks every N-th scene from the I-th")
    p.add_argument("--variants", nargs="*", type=pathlib.Path, default=None, metavar="SCENE",
                   help="check the image variants of these scene folders instead of the suite")
    p.add_argument("--summary", nargs="*", type=pathlib.Path, default=None,
                   help="only summarize these JSON-line files (of earlier shards) and exit")
    args = p.parse_args()
    if args.summary is not None:
        lines = [json.loads(line) for f in args.summary for line in f.read_text().splitlines() if line.startswith("{")]
        print(json.dumps(summarize([r for r in lines if r.get("benchmark") == "silhouette_check" and not r.get("summary")])))
        return
    try:
        i, n = (int(x) for x in args.shard.split("/"))
        assert 0 <= i < n
    except (ValueError, AssertionError):
        p.error(f"--shard must be I/N with 0 <= I < N, got {args.shard!r}")
    if args.null < 0:
        p.error(f"--null must be 0 or more, got {args.null}")
    if args.variants is not None:
        missing = [str(f) for f in args.variants if not (f / "all_data.json").is_file()]
        if missing or not args.variants:
            p.error(f"--variants needs scene folders with all_data.json; not found: {missing or 'no folder given'}")
        from toolkit.verbosity import configure_output

        configure_output(False)
        check_variants(args.variants, args.out)
        return

    import torch

    from toolkit.verbosity import configure_output

    configure_output(False)  # stdout holds only the JSON lines (no Warp banner or module-load lines)
    from toolkit.data.datamodule import resolve_cameras
    from toolkit.data.layout import load_scene
    from toolkit.discovery.hidden import PERTURBED_CAMERA, hidden_suite
    from toolkit.pipeline import training_frames
    from toolkit.scene.silhouette_agreement import silhouette_agreement

    records = []
    for hs in hidden_suite(n_null=args.null, size=args.size)[i::n]:
        folder = args.out / "scenes" / hs.name
        t = time.perf_counter()
        if not (folder / "all_data.json").is_file():
            hs.generate(folder)
        t_gen = time.perf_counter() - t
        scene = load_scene(folder)
        cams = resolve_cameras(scene, "sparse")
        frames = range(training_frames(scene, None))
        masks = {c: [torch.as_tensor(scene.load_mask(c, f) > 0.5) for f in frames] for c in cams}
        moved = cams[PERTURBED_CAMERA] if hs.effect == "camera_pose" else None
        claimed = scene.cameras if moved is None else scene.cameras.with_centre_moved(moved, hs.truth_strengths_vector())
        t = time.perf_counter()
        check = silhouette_agreement(claimed, masks, cams, frames)
        rec = {"benchmark": "silhouette_check", "scene": hs.name, "effect": hs.effect, "level": hs.level, "size": args.size,
               "moved_camera": moved, "generate_s": round(t_gen, 1), "check_s": round(time.perf_counter() - t, 1),
               **check.to_dict(), "named_right": check.suspect == moved}
        records.append(rec)
        print(json.dumps(rec), flush=True)
    print(json.dumps(summarize(records)), flush=True)


def summarize(records: list[dict]) -> dict:
    """False alarms (a camera named, or a disagreement, where no camera was moved) and the moved
    cameras named, per camera-pose level."""
    others = [r for r in records if r["moved_camera"] is None]
    out = {"benchmark": "silhouette_check", "summary": True, "scenes": len(records),
           "false_alarms": sum(r["suspect"] is not None for r in others), "disagreements_without_a_moved_camera":
           sum(bool(r["disagree"]) for r in others), "checked_without_a_moved_camera": len(others),
           "largest_pair_without_a_moved_camera": max((max(r["pairs"].values()) for r in others), default=None)}
    for level in sorted({r["level"] for r in records if r["moved_camera"] is not None}):
        moved = [r for r in records if r["moved_camera"] is not None and r["level"] == level]
        out[f"camera_pose_{level}_named"] = f"{sum(r['named_right'] for r in moved)} of {len(moved)}"
    return out


if __name__ == "__main__":
    main()
