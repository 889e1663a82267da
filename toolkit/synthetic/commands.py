"""``projo4d generate``: write synthetic scenes (PAC-NeRF layout) with honest ground truth.

::

    projo4d generate scene --shape torus --material neo_hookean --param E=1e5 --param nu=0.3 \\
        --v0 1,0,0 --effect air_drag.linear=0.5 --out DIR [--size small|full] [--seed S] [--device cpu]
    projo4d generate suite --out DIR --families neo_hookean sand --per-family 2 --size small --seed 0
    projo4d generate variant SCENE_DIR --out DIR --mask-noise 0.2 --calibration-deg 0.5 --gamma 1.2

Bad values are argparse errors (exit status 2) naming the value and the valid choices.
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

__all__ = ["configure", "run"]


# ---------------------------------------------------------------------------------- value parsers


def _number(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{what}: {text!r} is not a finite number")
    return value


def vector3(text: str) -> tuple[float, float, float]:
    """``"1,0,0"`` -> (1.0, 0.0, 0.0)."""
    parts = [p for p in text.replace(" ", "").split(",") if p != ""]
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected 3 comma-separated numbers such as 1,0,0, got {text!r}")
    return tuple(_number(p, f"in {text!r}") for p in parts)  # type: ignore[return-value]


def key_value(text: str) -> tuple[str, float]:
    """``"E=1e5"`` -> ("E", 100000.0)."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE such as E=1e5, got {text!r}")
    return key.strip(), _number(value.strip(), f"value of {key.strip()!r}")


def key_text(text: str) -> tuple[str, str]:
    """``"yield_rule=pacnerf"`` -> ("yield_rule", "pacnerf")."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    return key.strip(), value.strip()


def effect_assignment(text: str) -> tuple[str, str, str]:
    """``"air_drag.linear=0.5"`` -> ("air_drag", "linear", "0.5") (value parsed later)."""
    lhs, sep, value = text.partition("=")
    effect, dot, param = lhs.strip().partition(".")
    if not sep or not dot or not effect or not param:
        raise argparse.ArgumentTypeError(f"expected EFFECT.PARAM=VALUE such as air_drag.linear=0.5, got {text!r}")
    from toolkit.mpm.effects import EFFECTS

    names = EFFECTS.names()
    if effect not in names:
        raise argparse.ArgumentTypeError(f"unknown effect {effect!r} in {text!r} (choose from {', '.join(names)})")
    return effect, param, value.strip()


def resolution(text: str) -> tuple[int, int]:
    """``"400x300"`` (width x height) or ``"64"`` (square)."""
    parts = text.lower().split("x")
    try:
        dims = [int(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 400x400, got {text!r}") from None
    if len(dims) == 1:
        dims = dims * 2
    if len(dims) != 2 or min(dims) < 8:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT with both >= 8, got {text!r}")
    return dims[0], dims[1]


# ---------------------------------------------------------------------------------- parser


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the ``scene``, ``suite`` and ``variant`` subcommands to the ``generate`` parser."""
    from materials import MATERIALS
    from toolkit.synthetic.shapes import SHAPES
    from toolkit.synthetic.spec import SIZE_PRESETS
    from toolkit.synthetic.suite import FAMILY_RANGES, SHAPE_SETS

    sub = parser.add_subparsers(dest="what", metavar="{scene,suite,variant}", required=True)

    p = sub.add_parser("scene", help="one scene", description="Simulate, render and write one synthetic scene.")
    p.set_defaults(_parser=p)
    obj = p.add_argument_group("object")
    obj.add_argument("--shape", choices=list(SHAPES), default="torus", help="built-in shape (default torus)")
    obj.add_argument("--shape-size", type=key_value, action="append", default=[], metavar="NAME=METRES",
                     help="a size parameter of the shape, e.g. major_radius=0.12 (repeatable)")
    obj.add_argument("--mesh", type=Path, help="closed mesh file to use instead of --shape")
    obj.add_argument("--mesh-scale", type=float, default=1.0, help="mesh file units -> metres (default 1)")
    obj.add_argument("--position", type=vector3, metavar="X,Y,Z", help="bounding-box centre at rest, metres (default 0,0.35,0)")
    obj.add_argument("--rotation", type=vector3, metavar="RX,RY,RZ", help="rotation about world x, y, z, degrees")
    phys = p.add_argument_group("physics")
    phys.add_argument("--material", choices=MATERIALS.names(), default="neo_hookean", help="material (default neo_hookean)")
    phys.add_argument("--material-option", type=key_text, action="append", default=[], metavar="NAME=VALUE",
                      help="material option, e.g. yield_rule=pacnerf (repeatable)")
    phys.add_argument("--param", type=key_value, action="append", default=[], metavar="NAME=VALUE",
                      help="material parameter in physical units, e.g. E=1e5 (repeatable)")
    phys.add_argument("--density", type=float, help="kg/m^3 (default 1000)")
    phys.add_argument("--v0", type=vector3, metavar="VX,VY,VZ", help="initial velocity, m/s (default 0,0,0)")
    phys.add_argument("--gravity", type=vector3, metavar="GX,GY,GZ", help="m/s^2 (default 0,-9.8,0)")
    phys.add_argument("--effect", type=effect_assignment, action="append", default=[], metavar="EFFECT.PARAM=VALUE",
                      help="effect parameter, e.g. air_drag.linear=0.5 or wall.strength=1 (repeatable)")
    phys.add_argument("--effect-option", type=effect_assignment, action="append", default=[], metavar="EFFECT.OPTION=VALUE",
                      help="effect option, e.g. wall.normal=1,0,0 or wall.mode=slip (repeatable)")
    phys.add_argument("--boundary", choices=("sticky", "slip", "separate"), help="ground contact (default sticky)")
    video = p.add_argument_group("video and cameras")
    video.add_argument("--frames", type=int, help="frames to write (preset: full 20, small 10)")
    video.add_argument("--train-frames", type=int, help="of which for fitting (preset: full 14, small 7)")
    video.add_argument("--fps", type=float, help="frames per second (default 24)")
    video.add_argument("--cameras", type=int, help="number of cameras (preset: full 11, small 10)")
    video.add_argument("--resolution", type=resolution, metavar="WxH", help="image size (preset: full 400x400, small 64x64)")
    video.add_argument("--fov", type=float, metavar="DEG", help="vertical field of view (default 40; frames automatically)")
    video.add_argument("--camera-distance", type=float, metavar="M", help="camera distance to the target (default: automatic)")
    video.add_argument("--supersample", type=int, help="ray samples per pixel side (default 2)")
    video.add_argument("--no-ground", action="store_true", help="do not render the ground plane")
    truth = p.add_argument_group("truth resolution")
    truth.add_argument("--dx", type=float, help="grid spacing, metres (preset: full 0.008, small 0.02)")
    truth.add_argument("--particle-spacing", type=float, help="metres (default dx/2)")
    truth.add_argument("--substeps", type=int, help="minimum substeps per frame (default 200)")
    _common(p, SIZE_PRESETS)

    s = sub.add_parser("suite", help="a benchmark set over material families",
                       description="Generate (or complete) a benchmark suite across material families.")
    s.set_defaults(_parser=s)
    s.add_argument("--families", nargs="+", choices=list(FAMILY_RANGES), default=list(FAMILY_RANGES),
                   help="material families (default: all five)")
    s.add_argument("--per-family", type=int, default=2, help="scenes per family (default 2)")
    s.add_argument("--shape-set", choices=list(SHAPE_SETS), default="pac_nerf",
                   help="pac_nerf (default): a random shape per scene; spring_gaus: "
                        f"{', '.join(SHAPE_SETS['spring_gaus'])} in turn (stand-ins for the Spring-Gaus objects)")
    _common(s, SIZE_PRESETS)
    _configure_variant(sub)


def _configure_variant(sub) -> None:
    """``generate variant``: options mirror :class:`toolkit.synthetic.variants.VariantSpec`."""
    from toolkit.synthetic.variants import RENDER_STYLES, VariantSpec

    d = VariantSpec()
    v = sub.add_parser("variant", help="a perturbed copy of a scene folder",
                       description="Write a copy of a scene folder imaged differently (mask noise, calibration error, "
                                   "photometric change, frame-rate mismatch, render style) with its ground truth kept "
                                   "correct; definitions: toolkit.synthetic.variants.")
    v.set_defaults(_parser=v)
    v.add_argument("scene_dir", type=Path, metavar="SCENE_DIR", help="source scene (PAC-NeRF layout)")
    v.add_argument("--out", type=Path, required=True, help="output folder (new, empty, or an earlier variant)")
    v.add_argument("--mask-noise", type=float, default=d.mask_noise, metavar="P",
                   help=f"fraction of mask boundary pixels flipped per image, [0, 1] (default {d.mask_noise:g})")
    v.add_argument("--calibration-deg", type=float, default=d.calibration_deg, metavar="DEG",
                   help=f"rotation of each recorded camera about its centre, degrees (default {d.calibration_deg:g})")
    v.add_argument("--calibration-m", type=float, default=d.calibration_m, metavar="M",
                   help=f"displacement of each recorded camera centre, metres (default {d.calibration_m:g})")
    v.add_argument("--brightness", type=float, default=d.brightness, help=f"colour gain (default {d.brightness:g})")
    v.add_argument("--gamma", type=float, default=d.gamma, help=f"colour power x -> x**gamma (default {d.gamma:g})")
    v.add_argument("--tint", type=vector3, default=d.tint, metavar="R,G,B", help="per-channel gains (default 1,1,1)")
    v.add_argument("--blur-px", type=float, default=d.blur_px, metavar="SIGMA",
                   help=f"Gaussian blur of the colours, pixels (default {d.blur_px:g})")
    v.add_argument("--noise-std", type=float, default=d.noise_std, metavar="STD",
                   help=f"additive Gaussian colour noise, [0, 1] units (default {d.noise_std:g})")
    v.add_argument("--frame-stride", type=int, default=d.frame_stride, metavar="K",
                   help=f"keep frames 0, K, 2K, ... (default {d.frame_stride})")
    v.add_argument("--fps-scale", type=float, default=d.fps_scale, metavar="S",
                   help=f"the folder claims S times the true frame rate (default {d.fps_scale:g})")
    v.add_argument("--render-style", choices=RENDER_STYLES, default=d.render_style,
                   help=f"'points': re-render every frame as z-buffered particle discs from the truth point clouds "
                        f"(default {d.render_style})")
    v.add_argument("--seed", type=int, default=d.seed, help=f"seed of the random choices (default {d.seed})")
    v.add_argument("--quiet", action="store_true", help="no output but errors")


def variant_from_args(args: argparse.Namespace):
    """The :class:`~toolkit.synthetic.variants.VariantSpec` of ``projo4d generate variant`` arguments."""
    from toolkit.synthetic.variants import VariantSpec

    return VariantSpec(mask_noise=args.mask_noise, calibration_deg=args.calibration_deg, calibration_m=args.calibration_m,
                       brightness=args.brightness, gamma=args.gamma, tint=tuple(args.tint), blur_px=args.blur_px,
                       noise_std=args.noise_std, frame_stride=args.frame_stride, fps_scale=args.fps_scale, seed=args.seed,
                       render_style=args.render_style)


def _common(p: argparse.ArgumentParser, presets: dict) -> None:
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--size", choices=sorted(presets), default="small", help="resolution preset (default small)")
    p.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    p.add_argument("--device", default="cpu", help="Warp device, e.g. cpu or cuda:0 (default cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress output")


# ---------------------------------------------------------------------------------- run


def _effects(assignments, parser, what: str, numeric: bool) -> dict:
    out: dict = {}
    for effect, key, value in assignments:
        if numeric:
            try:
                parsed = float(value)
            except ValueError:
                parser.error(f"argument {what}: value of {effect}.{key} must be a number, got {value!r}")
        else:
            parsed = vector3(value) if "," in value else value
        out.setdefault(effect, {})[key] = parsed
    return out


def spec_from_args(args: argparse.Namespace):
    """The :class:`SceneSpec` that ``projo4d generate scene`` arguments describe."""
    from toolkit.synthetic.spec import SceneSpec

    parser = args._parser
    overrides: dict = {
        "shape": args.shape,
        "shape_size": dict(args.shape_size),
        "material": args.material,
        "material_options": dict(args.material_option),
        "params": dict(args.param),
        "effects": _effects(args.effect, parser, "--effect", True),
        "effect_options": _effects(args.effect_option, parser, "--effect-option", False),
        "seed": args.seed,
        "device": args.device,
        "mesh_scale": args.mesh_scale,
    }
    if args.mesh is not None:
        overrides["mesh_path"] = str(args.mesh)
    optional = {
        "position": args.position, "rotation_deg": args.rotation, "density": args.density, "v0": args.v0,
        "gravity": args.gravity, "boundary": args.boundary, "n_frames": args.frames, "n_train_frames": args.train_frames,
        "fps": args.fps, "n_cameras": args.cameras, "fov_y_deg": args.fov, "camera_distance": args.camera_distance,
        "supersample": args.supersample, "dx": args.dx, "particle_spacing": args.particle_spacing, "substeps": args.substeps,
    }
    overrides.update({k: v for k, v in optional.items() if v is not None})
    if args.resolution is not None:
        overrides["width"], overrides["height"] = args.resolution
    if args.no_ground:
        overrides["ground_plane"] = False
    if args.frames is not None and args.train_frames is None:
        overrides["n_train_frames"] = max(1, min(args.frames, round(args.frames * 0.7)))
    return SceneSpec.preset(args.size, **overrides)


def run(args: argparse.Namespace) -> int:
    """Run ``projo4d generate scene|suite|variant``; returns the exit status."""
    from toolkit.mpm import SimulationError
    from toolkit.synthetic.errors import SyntheticError

    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    logging.getLogger().setLevel(logging.WARNING if args.quiet else logging.INFO)  # the CLI installed a handler already
    parser = args._parser
    try:
        if args.what == "variant":
            from toolkit.synthetic.variants import make_variant

            root = make_variant(args.scene_dir, args.out, variant_from_args(args))
            if not args.quiet:
                print(f"wrote {root} (variant of {args.scene_dir}; what was done: {root / 'variant.json'})")
            return 0
        if args.what == "scene":
            from toolkit.synthetic.scene import generate_scene

            spec = spec_from_args(args)
            root = generate_scene(spec, args.out, progress=not args.quiet)
            print(f"wrote {root} ({spec.n_cameras} cameras x {spec.n_frames} frames, {spec.width}x{spec.height})")
            return 0
        from toolkit.synthetic.suite import generate_suite

        if args.per_family < 1:
            parser.error(f"argument --per-family: must be >= 1, got {args.per_family}")
        index = generate_suite(args.out, args.families, args.per_family, args.seed, args.size, args.device,
                               shape_set=args.shape_set, progress=not args.quiet)
        failed = [s["name"] for s in index["scenes"] if not s["complete"]]
        print(f"wrote {args.out / 'suite.json'}: {len(index['scenes']) - len(failed)} of {len(index['scenes'])} scenes complete")
        if failed:
            print(f"failed (rerun to retry): {', '.join(failed)}")
            return 1
        return 0
    except SyntheticError as exc:
        parser.error(str(exc))
    except SimulationError as exc:
        print(f"projo4d generate: the truth simulation failed: {exc}")
        return 1
    return 0
