"""``onfly render --scene NAME|PATH``: render one view of a scene to image files for a quick look."""

from __future__ import annotations

import argparse
from pathlib import Path

import math

from onfly.cli import CliError, echo

NAME = "render"
HELP = "render RGB, depth and instance ids of a scene from a pose (default: the start pose)"
DESCRIPTION = (
    "Render one frame of an embedded-world scene and write rgb.png, depth.npy (float32 metres, "
    "0 = no reading), depth_mm.png (uint16 millimetres), ids.png (instance ids, colour-coded) and "
    "ids_raw.png (uint16 instance ids); print the objects in view."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", required=True, help="committed scene name (see `onfly scenes`) or path to a scene .toml")
    parser.add_argument("--pose", default=None, help="body pose x,y,z,yaw (metres ENU, yaw in degrees counter-clockwise from east, as yaw_deg in scene and task files; negative numbers work: --pose -3,0,6,-90); default: the scene's start pose")
    parser.add_argument("--out", type=Path, default=Path("render_out"), help="output folder (created if missing)")
    parser.add_argument("--width", type=int, default=640, help="image width in pixels")
    parser.add_argument("--height", type=int, default=427, help="image height in pixels")
    parser.add_argument("--time", type=float, default=0.0, help="world-clock time in seconds that places the scene's moving people (default 0)")


def parse_pose(text: str):
    """``"x,y,z,yaw"`` (metres, degrees) -> (position (3,) array, yaw radians)."""
    import numpy as np

    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise CliError(f"--pose must be four numbers x,y,z,yaw, got {text!r}") from None
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
        raise CliError(f"--pose must be four finite numbers x,y,z,yaw, got {text!r}")
    return np.array(vals[:3]), math.radians(vals[3])


def id_colors(ids):
    """Colour-code an int id image (H, W) as uint8 RGB; 0 (background) is black."""
    import numpy as np

    lut = np.random.default_rng(0).integers(40, 256, size=(int(ids.max()) + 1, 3), dtype=np.uint8)
    lut[0] = 0
    return lut[ids]


def run(args: argparse.Namespace) -> int:
    if args.width <= 0 or args.height <= 0:
        raise CliError(f"--width and --height must be positive, got {args.width} x {args.height}")
    pose = None if args.pose is None else parse_pose(args.pose)
    if not math.isfinite(args.time):
        raise CliError(f"--time must be a finite number of seconds, got {args.time}")
    import cv2
    import numpy as np

    from onfly.world.geometry import SceneGeometry
    from onfly.world.render import Renderer
    from onfly.world.scene import SceneFormatError, load_scene, resolve_scene
    from planning.camera import PinholeCamera
    from planning.frames import body_transform, cam_transform_from_body

    try:
        scene = load_scene(resolve_scene(args.scene))
    except (FileNotFoundError, SceneFormatError) as exc:
        raise CliError(f"--scene: {exc}") from None
    p, yaw = (scene.start.position_m, scene.start.yaw_rad) if pose is None else pose
    camera = PinholeCamera.from_fov(args.width, args.height, 90.0, 60.0)
    renderer = Renderer(SceneGeometry(scene), camera)
    result = renderer.render(cam_transform_from_body(body_transform(p, yaw)), t_s=args.time)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out / "rgb.png"), result.rgb[:, :, ::-1])
    np.save(out / "depth.npy", result.depth_m)
    cv2.imwrite(str(out / "depth_mm.png"), np.clip(np.round(result.depth_m * 1000.0), 0, 65535).astype(np.uint16))
    cv2.imwrite(str(out / "ids.png"), id_colors(result.instance_ids)[:, :, ::-1])
    cv2.imwrite(str(out / "ids_raw.png"), result.instance_ids.astype(np.uint16))
    ann = renderer.annotate(result)
    counts = np.bincount(result.instance_ids.ravel())
    echo(f"scene {scene.name}: pose ({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}) yaw {yaw:.3f} rad, t = {args.time:g} s -> {out}/")
    echo(f"{'id':>5}  {'pixels':>7}  {'label':<16} name")
    for iid, vo in sorted(ann.objects.items(), key=lambda kv: -counts[kv[0]]):
        echo(f"{iid:>5}  {counts[iid]:>7}  {vo.label:<16} {vo.name}")
    return 0
