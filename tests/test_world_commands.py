"""`onfly render` and `onfly scenes`: files written match a direct render; errors are one line."""

from __future__ import annotations

import json

import cv2
import numpy as np

from onfly.cli import main
from onfly.world import World


def test_render_writes_images_that_match_the_renderer(tmp_path, capsys):
    # yaw in degrees, as in scene and task files
    assert main(["render", "--scene", "corridor", "--pose", "3,0.5,1.2,17", "--out", str(tmp_path), "--width", "160", "--height", "107"]) == 0
    from onfly.world.render import Renderer
    from planning.camera import PinholeCamera
    from planning.frames import body_transform, cam_transform_from_body

    w = World.from_scene("corridor")
    ref = Renderer(w.geometry, PinholeCamera.from_fov(160, 107, 90, 60)).render(cam_transform_from_body(body_transform([3, 0.5, 1.2], np.radians(17.0))))
    rgb = cv2.imread(str(tmp_path / "rgb.png"))[:, :, ::-1]
    np.testing.assert_array_equal(rgb, ref.rgb)
    np.testing.assert_array_equal(np.load(tmp_path / "depth.npy"), ref.depth_m)
    mm = cv2.imread(str(tmp_path / "depth_mm.png"), cv2.IMREAD_UNCHANGED)
    assert mm.dtype == np.uint16
    np.testing.assert_array_equal(mm, np.round(ref.depth_m * 1000).astype(np.uint16))
    ids = cv2.imread(str(tmp_path / "ids_raw.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(ids, ref.instance_ids)
    assert cv2.imread(str(tmp_path / "ids.png")).shape == (107, 160, 3)
    out = capsys.readouterr().out
    assert "corridor walls" in out and "scene corridor" in out


def test_render_rejects_a_bad_pose_and_an_unknown_scene(tmp_path, capsys):
    assert main(["render", "--scene", "villa", "--pose", "1,2,nan,0", "--out", str(tmp_path)]) == 2
    assert "--pose must be four finite numbers" in capsys.readouterr().err
    assert main(["render", "--scene", "atlantis", "--out", str(tmp_path)]) == 2
    assert "no scene named 'atlantis'" in capsys.readouterr().err


def test_scenes_lists_all_committed_scenes(capsys):
    assert main(["scenes", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 14  # the paper's ten, the three harder scenes of issue 16, the crowd scene of issue 19
    assert next(r for r in rows if r["name"] == "station_concourse")["actors"] == 8
    assert next(r for r in rows if r["name"] == "villa")["actors"] == 0
    villa = next(r for r in rows if r["name"] == "villa")
    assert villa["objects"] == len(World.from_scene("villa").scene.objects)
    assert "pool edge" in villa["target_names"] and villa["bounds_max_m"] == [19.0, 19.0, 10.0]


def test_render_places_walkers_at_the_given_time(tmp_path, capsys):
    """--time moves the scene's walkers: the concourse start view at 0 s and at 20 s differ in the
    pixels of a passenger, and match a direct render at those times."""
    from onfly.world.render import Renderer
    from onfly.world.scene import load_scene, resolve_scene
    from onfly.world.geometry import SceneGeometry
    from planning.camera import PinholeCamera
    from planning.frames import body_transform, cam_transform_from_body

    scene = load_scene(resolve_scene("station_concourse"))
    cam = PinholeCamera.from_fov(160, 107, 90.0, 60.0)
    r = Renderer(SceneGeometry(scene), cam)
    T = cam_transform_from_body(body_transform(scene.start.position_m, scene.start.yaw_rad))
    ids = {}
    for t in (0.0, 20.0):
        out = tmp_path / f"t{t:g}"
        assert main(["render", "--scene", "station_concourse", "--width", "160", "--height", "107", "--time", str(t), "--out", str(out)]) == 0
        ids[t] = cv2.imread(str(out / "ids_raw.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(ids[t], r.render(T, t_s=t).instance_ids)
    walkers = [a.instance_id for a in scene.actors]
    assert np.isin(ids[0.0], walkers).any() and not np.array_equal(np.isin(ids[0.0], walkers), np.isin(ids[20.0], walkers))
    assert main(["render", "--scene", "station_concourse", "--time", "nan", "--out", str(tmp_path / "x")]) == 2
    assert "--time must be a finite number" in capsys.readouterr().err
