"""``eva render`` and ``eva animate`` as a user runs them: an avatar directory (the part-coloured
teacher avatar of ``scenes``, saved with training frames) -> a PNG in a pose, and an
mp4 of the avatar performing a JSON motion or a video of a different synthetic person (another
body shape and look from the synthetic benchmark, through MediaPipe and the body fit). Checked:
sizes, frame counts, that frames change exactly when the motion does, and every bad input."""

from __future__ import annotations

import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers import service as svc
from helpers.scenes import front_camera, random_params, teacher_avatar
from PIL import Image
from typer.testing import CliRunner

from eva_engine.avatar import AvatarFrames, TrainingRecord, read_avatar_meta, save_avatar
from eva_engine.avatar.coverage import Coverage
from eva_engine.cli import app
from eva_engine.data import read_video, write_video

other_signer_video = svc.other_signer_video  # a fixture
RAISED = {
    "joints": {"upperarm01.L": [0.0, 0.0, 1.2], "lowerarm01.L": [0.0, -1.0, 0.0]},
    "expression": {"jawOpen": 0.6},
}


@pytest.fixture(scope="module")
def avatar_dir(anny_model, tmp_path_factory):
    """A saved avatar with 3 training frames (80 x 64 px, their poses and cameras) and the
    coverage a training run records of them."""
    folder = tmp_path_factory.mktemp("cli") / "avatar"
    avatar = teacher_avatar(anny_model, n=3000)
    cam = front_camera(64)
    frames = AvatarFrames(
        params=random_params(anny_model, 3, seed=2),
        K=cam.K.expand(3, 3, 3),
        viewmat=cam.viewmat.expand(3, 4, 4),
        timestamps=torch.tensor([0.0, 0.1, 0.2], dtype=torch.float64),
        image_size=(80, 64),
        fps=10.0,
    )
    record = TrainingRecord(coverage=Coverage.of_frames(anny_model, frames.params, frames.viewmat))
    save_avatar(avatar, folder, record, frames=frames)
    return folder


def _run(*args) -> SimpleNamespace:
    res = CliRunner().invoke(app, [str(a) for a in args])
    return SimpleNamespace(code=res.exit_code, out=" ".join(res.output.split()))  # unwrapped by rich


def _png(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB")).astype(int)


def test_render_a_pose_from_json(avatar_dir, tmp_path):
    (tmp_path / "pose.json").write_text(json.dumps(RAISED))
    rest, posed = tmp_path / "rest.png", tmp_path / "posed.png"
    assert _run("render", avatar_dir, "--out", rest, "--width", 96, "--height", 128).code == 0
    size = ("--width", 96, "--height", 128)
    res = _run("render", avatar_dir, "--pose", tmp_path / "pose.json", "--out", posed, *size)
    assert res.code == 0, res.out
    assert "wrote" in res.out
    a, b = _png(rest), _png(posed)
    assert a.shape == b.shape == (128, 96, 3)
    assert np.abs(a - b).mean() > 1.0  # the arm moved
    person = np.abs(a - 255).sum(-1) > 30
    assert 0.05 < person.mean() < 0.8  # framed on the avatar: it fills the picture, not lost in it
    # Inline JSON is the same pose.
    inline = tmp_path / "inline.png"
    assert (
        _run(
            "render",
            avatar_dir,
            "--pose",
            json.dumps(RAISED),
            "--out",
            inline,
            "--width",
            96,
            "--height",
            128,
        ).code
        == 0
    )
    assert np.array_equal(_png(inline), b)


def test_render_beyond_the_training_range_warns_and_still_renders(avatar_dir, tmp_path):
    """The training frames face the camera with the arms near rest: a raised arm seen from the
    side renders, with a warning naming the joint and the camera; a training frame has none."""
    out = tmp_path / "side.png"
    res = _run("render", avatar_dir, "--pose", json.dumps(RAISED), "--camera", "left", "--out", out)
    assert res.code == 0 and out.is_file(), res.out
    # About 90 deg: the framed camera turns about the avatar's centre, not exactly about its root.
    assert (
        re.search(r"warning: the camera is at yaw (8[5-9]|9[0-5]) deg", res.out) and "upperarm01.L" in res.out
    )
    assert "jawOpen" in res.out  # the expression too: training kept a neutral face
    res = _run("render", avatar_dir, "--pose", "frame:1", "--out", tmp_path / "frame.png")
    assert res.code == 0 and "warning" not in res.out


def test_render_frames_cameras_and_backgrounds(avatar_dir, tmp_path):
    out = tmp_path / "frame.png"
    res = _run("render", avatar_dir, "--pose", "frame:1", "--out", out)
    assert res.code == 0, res.out
    assert _png(out).shape == (80, 64, 3)  # the training frame's own size and camera
    side = tmp_path / "side.jpg"
    assert (
        _run(
            "render",
            avatar_dir,
            "--camera",
            "left",
            "--background",
            "black",
            "--out",
            side,
            "--width",
            64,
            "--height",
            64,
        ).code
        == 0
    )
    img = _png(side)
    assert img[0, 0].sum() < 30 and (img.sum(-1) > 60).mean() > 0.02  # black around a person
    cam = {"yaw": 30, "pitch": 10, "distance": 3.0, "target": [0, 0.2, 0]}
    custom = tmp_path / "custom.png"
    assert _run("render", avatar_dir, "--camera", json.dumps(cam), "--out", custom, "--width", 64).code == 0
    assert _png(custom).shape == (512, 64, 3)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--pose", '{"joints": {"tail": [0, 0, 1]}}'], "tail"),
        (["--pose", '{"joints": {"upperarm01.L": [0, 1]}}'], "joints"),
        (["--pose", "{not json"], "not valid JSON"),
        (["--pose", "missing.json"], "no pose file"),
        (["--pose", "frame:99"], "out of range"),
        (["--camera", "sideways"], "unknown camera"),
        (["--camera", '{"pitch": 95}'], "pitch"),
        (["--background", "purple"], "not a colour"),
        (["--width", "8"], "width"),
    ],
)
def test_render_bad_input_is_a_clear_error(avatar_dir, tmp_path, args, needle):
    res = _run("render", avatar_dir, "--out", tmp_path / "x.png", *args)
    assert res.code == 2 and needle in res.out, res.out
    assert not (tmp_path / "x.png").exists()


def test_render_needs_an_avatar_and_an_image_file(avatar_dir, tmp_path):
    res = _run("render", tmp_path / "nobody", "--out", tmp_path / "x.png")
    assert res.code == 2 and "no avatar directory" in res.out
    res = _run("render", avatar_dir, "--out", tmp_path / "x.gif")
    assert res.code == 2 and ".png" in res.out


def _frames(path) -> np.ndarray:
    return read_video(path).frames.astype(int)


def test_animate_a_json_motion(avatar_dir, tmp_path):
    """Three frames at rest, then three raising the arm: the video changes exactly at the switch."""
    motion = tmp_path / "motion.json"
    motion.write_text(json.dumps({"fps": 10, "poses": [{}, {}, {}, RAISED, RAISED, RAISED]}))
    out = tmp_path / "motion.mp4"
    res = _run("animate", avatar_dir, motion, "--out", out, "--width", 96, "--height", 128, "--smooth", 0)
    assert res.code == 0, res.out
    assert "6 frames 96x128 at 10 fps" in res.out
    clip = read_video(out)
    assert clip.frames.shape == (6, 128, 96, 3) and clip.fps == pytest.approx(10.0)
    f = clip.frames.astype(int)
    change = [np.abs(f[i + 1] - f[i]).mean() for i in range(5)]
    assert max(change[0], change[1], change[3], change[4]) < 0.5, change  # a held pose is a still picture
    assert change[2] > 4 * max(max(change[0], change[1], change[3], change[4]), 0.25), change
    # --fps resamples the motion in time: 0.5 s at 20 fps is 11 frames, the switch eased over one.
    res = _run(
        "animate",
        avatar_dir,
        motion,
        "--out",
        tmp_path / "fast.mp4",
        "--width",
        64,
        "--height",
        64,
        "--fps",
        20,
        "--smooth",
        0,
    )
    assert res.code == 0, res.out
    assert _frames(tmp_path / "fast.mp4").shape[0] == 11


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--camera", "driving"], "needs a driving video"),
        (["--side-by-side"], "needs a driving video"),
        (["--camera", "sideways"], "unknown camera"),
        (["--smooth", "-1"], "smooth"),
    ],
)
def test_animate_bad_options_are_clear_errors(avatar_dir, tmp_path, args, needle):
    motion = tmp_path / "m.json"
    motion.write_text(json.dumps([{}, RAISED]))
    res = _run("animate", avatar_dir, motion, "--out", tmp_path / "x.mp4", *args)
    assert res.code == 2 and needle in res.out, res.out
    assert not (tmp_path / "x.mp4").exists()


def test_animate_bad_driving_input_is_a_clear_error(avatar_dir, tmp_path):
    (tmp_path / "bad.json").write_text('{"poses": [{"joints": {"wing.L": [0, 0, 1]}}]}')
    res = _run("animate", avatar_dir, tmp_path / "bad.json", "--out", tmp_path / "x.mp4")
    assert res.code == 2 and "wing.L" in res.out
    res = _run("animate", avatar_dir, tmp_path / "none.mp4", "--out", tmp_path / "x.mp4")
    assert res.code == 2 and "no such file" in res.out
    (tmp_path / "junk.mp4").write_bytes(b"not a video at all")
    res = _run("animate", avatar_dir, tmp_path / "junk.mp4", "--out", tmp_path / "x.mp4")
    assert res.code == 2 and "error" in res.out
    empty = np.zeros((3, 96, 96, 3), np.uint8) + 128
    write_video(tmp_path / "nobody.mp4", empty, fps=5)
    res = _run("animate", avatar_dir, tmp_path / "nobody.mp4", "--out", tmp_path / "x.mp4")
    assert res.code == 2 and "no person" in res.out
    res = _run("animate", avatar_dir, tmp_path / "bad.json", "--out", tmp_path / "x.avi")
    assert res.code == 2 and ".mp4" in res.out


@pytest.mark.slow
def test_animate_with_a_video_of_someone_else(avatar_dir, other_signer_video, tmp_path):
    out = tmp_path / "side.mp4"
    res = _run(
        "animate",
        avatar_dir,
        other_signer_video,
        "--out",
        out,
        "--side-by-side",
        "--camera",
        "driving",
        "--fit-scale",
        "0.1",
        "--smooth",
        0,
    )
    assert res.code == 0, res.out
    f = _frames(out)
    assert f.shape == (8, 256, 512, 3)  # every driving frame, the driving frame | the avatar
    driving, avatar = f[..., :256, :], f[..., 256:, :]
    person = np.abs(driving - 255).sum(-1) > 40
    shown = np.abs(avatar - 255).sum(-1) > 40
    # Through the driving camera, the avatar stands where the person stood, at their size.
    iou = (person & shown).sum((1, 2)) / (person | shown).sum((1, 2))
    assert iou.min() > 0.3, iou
    # It moves as the person does: every new driving pose is a new avatar picture.
    moves = np.array([np.abs(avatar[i + 1] - avatar[i]).mean() for i in range(7)])
    assert moves.min() > 0.5, moves
    # From the front, framed on the avatar (an orbit camera), at the driving frame's height.
    front = tmp_path / "front.mp4"
    res = _run("animate", avatar_dir, other_signer_video, "--out", front, "--fit-scale", "0.1", "--fps", 4)
    assert res.code == 0, res.out
    g = _frames(front)
    assert g.shape == (15, 256, 256, 3)  # 3.5 s at 4 fps
    assert np.abs(np.diff(g, axis=0)).mean((1, 2, 3)).min() > 0.05
    assert read_avatar_meta(avatar_dir).format == "eva-avatar"  # the avatar itself is untouched
