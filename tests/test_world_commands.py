"""`onfly render` and `onfly scenes`: files written match a direct render; errors are one line."""

from __future__ import annotations

import json

import cv2
import numpy as np

from onfly.cli import main
from onfly.world import World


def test_render_writes_images_that_match_the_renderer(tmp_path, capsys):
    assert main(["render", "--scene", "corridor", "--pose", "3,0.5,1.2,0.3", "--out", str(tmp_path), "--width", "160", "--height", "107"]) == 0
    from onfly.world.render import Renderer
    from planning.camera import PinholeCamera
    from planning.frames import body_transform, cam_transform_from_body

    w = World.from_scene("corridor")
    ref = Renderer(w.geometry, PinholeCamera.from_fov(160, 107, 90, 60)).render(cam_transform_from_body(body_transform([3, 0.5, 1.2], 0.3)))
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
