"""The videos a job refuses instead of training a garbage avatar (issue 41): the rules of
``align.input_checks`` on their own, then real MediaPipe on rendered clips of each refusal case
(``synth.hard``: a hand alone, two people side by side, a person too small), each refused with
its reason before the fit, and a clip with too few frames with a person refused by a job's checks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eva_engine.align import InputChecks, PreprocessConfig, PreprocessError, preprocess_video
from eva_engine.align.input_checks import body_found, person_height, refusal_reason
from eva_engine.synth.hard import HARD_CASES, REFUSAL_CASES, HardVideo, hard_scene, render_hard_video

BODY = {"pose": True, "face": True, "left_hand": False, "right_hand": True}
POSE_ALONE = {"pose": True, "face": False, "left_hand": False, "right_hand": False}


def test_a_body_is_a_pose_confirmed_by_the_face_or_a_hand():
    assert body_found(BODY) and not body_found(POSE_ALONE) and not body_found({})
    assert body_found({"pose": True, "left_hand": True}) and not body_found({"face": True, "left_hand": True})


def test_person_height_from_the_mask_else_the_keypoints():
    mask = np.zeros((100, 50), np.float32)
    mask[20:71, 10:20] = 1.0
    kp = np.array([[5.0, 10.0, 1.0], [5.0, 90.0, 1.0], [5.0, 99.0, 0.0]])
    assert person_height(mask, kp) == 51.0
    assert person_height(None, kp) == 80.0  # the invisible point does not count
    assert person_height(np.zeros((4, 4)), kp[:1]) is None


def test_each_rule_gives_its_reason_and_a_good_clip_none():
    checks = InputChecks(min_frames=8)
    good = refusal_reason(checks, [BODY] * 10, list(range(10)), [200.0] * 10, [False] * 8)
    assert good is None
    short = refusal_reason(checks, [BODY] * 5 + [{}] * 5, list(range(5)), [200.0] * 5)
    assert short is not None and "found in 5 of the video's 10 frames; an avatar needs at least 8" in short
    hand = refusal_reason(checks, [POSE_ALONE] * 9 + [BODY], list(range(10)), [200.0] * 10)
    assert hand is not None and "a body was found in only 1 of 10 frames" in hand
    small = refusal_reason(checks, [BODY] * 10, list(range(10)), [60.0] * 9 + [None])
    assert small is not None and "only 60 px tall" in small and "80 px" in small
    crowd = refusal_reason(checks, [BODY] * 10, list(range(10)), [200.0] * 10, [True] * 5 + [False] * 3)
    assert crowd is not None and "another person is in 5 of 8 frames" in crowd
    # Someone walking past in a few frames is not a crowd.
    assert (
        refusal_reason(checks, [BODY] * 10, list(range(10)), [200.0] * 10, [True] * 2 + [False] * 6) is None
    )


def test_input_checks_reject_nonsense():
    with pytest.raises(ValueError):
        InputChecks(min_frames=0)
    with pytest.raises(ValueError):
        InputChecks(min_body_share=1.5)


@pytest.fixture(scope="module")
def refusal_clips(anny_model, tmp_path_factory) -> dict[str, HardVideo]:
    root = tmp_path_factory.mktemp("refusals")
    sizes = {"hand_alone": (12, 256), "two_people": (8, 256), "too_small": (8, 256)}
    return {
        name: render_hard_video(name, 0, root / name, frames=n, size=size, model=anny_model, texture_size=512)
        for name, (n, size) in sizes.items()
    }


@pytest.mark.parametrize(
    ("case", "reason"),
    [
        ("hand_alone", "a body was found in only"),
        ("two_people", "another person is in"),
        ("too_small", "px tall in the frames"),
    ],
)
def test_each_refusal_case_ends_in_its_reason_not_a_dataset(
    refusal_clips, anny_model, tmp_path, case, reason
):
    assert case in REFUSAL_CASES
    with pytest.raises(PreprocessError, match=reason):
        preprocess_video(refusal_clips[case].video, tmp_path / "ds", PreprocessConfig(), model=anny_model)
    assert not (tmp_path / "ds").exists()


def test_a_job_refuses_a_clip_with_too_few_frames_with_a_person(anny_model, tmp_path):
    """A job's checks (``JobOptions.preprocess_config``) need ``MIN_FRAMES`` frames with a person;
    the engine's own default takes any."""
    from jobs.options import MIN_FRAMES, JobOptions

    clip = render_hard_video("clean", 0, tmp_path / "clip", frames=MIN_FRAMES - 2, size=256, model=anny_model)
    config = JobOptions().preprocess_config(MIN_FRAMES - 2)
    with pytest.raises(PreprocessError, match=f"an avatar needs at least {MIN_FRAMES}"):
        preprocess_video(clip.video, tmp_path / "ds", config, model=anny_model)
    report = preprocess_video(clip.video, tmp_path / "ds", PreprocessConfig(fit=False), model=anny_model)
    assert report.kept_frames == MIN_FRAMES - 2


def test_a_hard_clip_comes_with_its_truth(anny_model, tmp_path):
    """The blurred clip's frames are the mean over its shutter; its truth is the sharp instant:
    the two differ where the hands move and agree on the background."""
    clip = render_hard_video(
        "blur", 0, tmp_path / "blur", frames=4, size=96, model=anny_model, texture_size=256
    )
    import av

    with av.open(str(clip.video)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 4 and len(clip.times) == 4 and HardVideo.load(tmp_path / "blur").fps == clip.fps
    truth, mask = clip.truth(1)
    assert truth.shape == (96, 96, 3) and mask.shape == (96, 96) and mask.max() == 255
    import cv2

    diff = np.abs(frames[1].astype(float) - truth.astype(float)).mean(axis=2)
    far = cv2.dilate(mask, np.ones((15, 15), np.uint8)) == 0  # beyond where the blur reaches
    assert diff[far].mean() < 3.0  # codec noise only
    assert diff[mask > 0].mean() > 2 * diff[far].mean()
    assert set(HARD_CASES) == {"clean", "closeup", "cropped", "blur", "dark", "second_person"}


def test_a_hard_clips_scene_is_the_truth_it_rendered(anny_model, tmp_path):
    """``hard_scene`` gives the poses and camera the clip was rendered with: the body posed and
    filmed by them covers each frame's true mask (what a perfect fit would give)."""
    from eva_engine.render.mesh import MeshRenderConfig, MeshRenderer

    clip = render_hard_video(
        "closeup", 1, tmp_path / "c", frames=3, size=96, model=anny_model, texture_size=256
    )
    scene = hard_scene("closeup", 1, frames=3, size=96, model=anny_model)
    assert scene.sharp_params.batch_size == 3 and scene.viewmat.shape == (3, 4, 4) and scene.K.shape == (3, 3)
    with torch.no_grad():
        vertices = anny_model(scene.sharp_params).vertices
    config = MeshRenderConfig(width=96, height=96, supersample=1)
    with MeshRenderer(anny_model.faces, config) as renderer:
        renderer.set_surface(colors=np.ones((anny_model.num_vertices, 3), np.float32))
        for i in range(3):
            body = renderer.render(vertices[i], scene.viewmat[i], scene.K).alpha.numpy() > 0.5
            person = clip.truth(i)[1] > 127
            assert (body & person).sum() / (body | person).sum() > 0.97
