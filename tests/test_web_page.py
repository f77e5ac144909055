"""The web page in a real browser, as a person uses it: Debian's Chromium, headless, driven by
Selenium through ``chromium-driver``, against a real ``eva serve`` and ``eva worker``. Load the
page, upload the demo's synthetic signer video, watch the job to the end, move sliders and see
the avatar change, animate it with a video of someone else and play the result. Screenshots go to
``out/web_page_*.png`` for a person to look at. Then ``eva render`` and ``eva animate`` on the
avatar the service made."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import httpx
import numpy as np
import pytest
from helpers import service as svc
from helpers.service import EVA, free_port, log_tail, start_process, start_worker, stop, wait_for
from PIL import Image

from jobs.options import JobOptions
from service import headless_browser

signer_video = svc.signer_video  # fixtures
other_signer_video = svc.other_signer_video

pytestmark = pytest.mark.slow
OUT = Path(__file__).resolve().parent.parent / "out"


def _browser():
    if reason := headless_browser.missing():
        pytest.skip(reason)
    return headless_browser.start_chromium()


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    data = tmp_path_factory.mktemp("web")
    port = free_port()
    logs = SimpleNamespace(server=data / "serve.log", worker=data / "worker.log")
    server = start_process([EVA, "serve", "--port", str(port), "--data-dir", str(data)], logs.server)
    worker = start_worker(data, logs.worker)
    driver = profile = None
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60.0) as api:

            def healthy():
                try:
                    return api.get("/healthz").status_code == 200
                except httpx.TransportError:
                    assert server.poll() is None, log_tail(logs.server)
                    return False

            wait_for(healthy, 90, "eva serve to answer /healthz")
            driver, profile = _browser()
            OUT.mkdir(exist_ok=True)
            url = f"http://127.0.0.1:{port}/"
            yield SimpleNamespace(url=url, driver=driver, api=api, data=data, logs=logs)
    finally:
        if driver is not None:
            driver.quit()
        if profile:
            shutil.rmtree(profile, ignore_errors=True)
        stop(worker)
        stop(server)


def _by(css: str):
    from selenium.webdriver.common.by import By

    return By.CSS_SELECTOR, css


def _renders(driver) -> int:
    return int(driver.find_element(*_by("#pose-image")).get_attribute("data-renders"))


def _idle(driver) -> bool:
    """No render in flight and none waiting: the full image of the sliders is shown."""
    return not driver.execute_script("return state.rendering || state.dirty || state.moving || !state.sharp")


# Records each new image of the pose panel: its size and whether the page asked for a preview.
RECORD_RENDERS = """
window.shown = [];
const img = document.getElementById("pose-image");
new MutationObserver(() => shown.push([img.dataset.detail, img.naturalWidth, img.naturalHeight]))
  .observe(img, {attributes: true, attributeFilter: ["data-renders"]});
"""


def _image(driver) -> np.ndarray:
    png = driver.find_element(*_by("#pose-image")).screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


@pytest.fixture(scope="module")
def avatar(site, signer_video):
    """Upload the demo's signer through the page's form and follow the job on the page."""
    from selenium.webdriver.support.ui import Select

    d = site.driver
    d.get(site.url)
    assert d.title == "EVA avatars"
    d.find_element(*_by("#video-input")).send_keys(str(signer_video))
    # The forms' choices and bounds come from GET /page/options once the page has loaded.
    wait_for(lambda: len(d.find_elements(*_by("#preset option"))) > 0, 30, "the form options")
    preset = Select(d.find_element(*_by("#preset")))
    assert preset.first_selected_option.get_attribute("value") == "fast"  # JobOptions' default
    assert d.find_element(*_by("#image-scale")).get_attribute("max") == "1"
    assert d.find_element(*_by("#image-scale")).get_attribute("min") == "0.06"  # gt 0.05, step 0.01
    preset.select_by_value("tiny")
    d.find_element(*_by("#new-avatar summary")).click()
    fast = svc.FAST_OPTIONS
    for field, value in (
        ("iterations", fast["iterations"]),
        ("image-scale", fast["image_scale"]),
        ("max-frames", fast["max_frames"]),
        ("fit-scale", fast["fit_scale"]),
    ):
        d.find_element(*_by(f"#{field}")).send_keys(value)
    # Close-ups asked for on a video no larger than its frames: none are cut, the avatar is made.
    closeups = d.find_element(*_by("#face-closeups"))
    assert not closeups.is_selected()  # JobOptions' default
    tooltip = d.execute_script("return arguments[0].closest('label').title", closeups)
    assert tooltip == JobOptions.model_fields["face_closeups"].description
    closeups.click()
    d.find_element(*_by("#upload-button")).click()
    stages = set()
    # The page redraws its lists as the job goes on: read them in the page, not by element handles.
    read = """return {stages: [...document.querySelectorAll('#jobs .job .state')].map(e => e.textContent),
                      cards: [...document.querySelectorAll('.avatar-card')].map(e => [e.dataset.avatarId,
                              e.dataset.status, e.textContent])}"""

    def job_done():
        seen = d.execute_script(read)
        stages.update(seen["stages"])
        return [c for c in seen["cards"] if c[1] in ("ready", "failed")]

    (avatar_id, status, text), *_ = wait_for(job_done, 300, "the avatar job to finish on the page", every=0.5)
    assert status == "ready", (text, log_tail(site.logs.worker))
    d.save_screenshot(str(OUT / "web_page_uploaded.png"))
    return SimpleNamespace(id=avatar_id, stages=stages)


def test_upload_shows_the_job_live_and_the_avatar(site, avatar):
    d = site.driver
    assert any(s.startswith("running") for s in avatar.stages), avatar.stages  # seen while it ran
    job = d.execute_script("return document.querySelector('#jobs .job').textContent")
    assert "succeeded" in job and "100%" in job
    card = f'.avatar-card[data-avatar-id="{avatar.id}"]'
    text = d.execute_script(f"return document.querySelector('{card}').textContent")
    assert "signer.mp4" in text and "Gaussians" in text
    assert "dB on unseen poses" in text  # the held-out score, not the training frames' fit
    # The quality verdict as a badge; a 6-iteration avatar is not good, and the card says why.
    badge = d.execute_script(f"return document.querySelector('{card} .badge').textContent")
    assert badge in ("fair", "poor"), badge
    reasons = d.execute_script(f"return document.querySelector('{card} .reasons').textContent")
    assert "frames it never trained on" in reasons, reasons
    thumb = f"const i = document.querySelector('{card} img'); return i && i.complete && i.naturalWidth"
    assert wait_for(lambda: d.execute_script(thumb), 60, "the avatar's thumbnail") > 0


def test_move_sliders_and_the_avatar_changes(site, avatar):
    from selenium.webdriver.common.keys import Keys

    d = site.driver
    card = d.find_element(*_by(f'.avatar-card[data-avatar-id="{avatar.id}"]'))
    if "selected" not in card.get_attribute("class"):  # the page selects the first avatar made
        card.click()
    wait_for(lambda: _renders(d) >= 1 and _idle(d), 60, "the first render of the pose panel")
    before, count = _image(d), _renders(d)
    assert (np.abs(before - 255).sum(-1) > 40).mean() > 0.03  # the avatar is in the picture
    d.execute_script(RECORD_RENDERS)
    # A person drags the slider; here the keyboard moves it (each key press is an input event).
    for name, keys in (
        ("arm_out.L", [Keys.ARROW_RIGHT] * 35),
        ("elbow.R", [Keys.ARROW_RIGHT] * 40),
        ("smile", [Keys.END]),
    ):
        slider = d.find_element(*_by(f'input[data-control="{name}"]'))
        d.execute_script("arguments[0].scrollIntoView({block: 'center'})", slider)
        slider.click()
        slider.send_keys(*keys)
    values = json.loads(d.execute_script("return JSON.stringify(state.values)"))
    assert values["arm_out.L"] > 0.5 and values["smile"] == 1.0
    wait_for(lambda: _renders(d) > count and _idle(d), 60, "the re-render after moving the sliders")
    after = _image(d)
    assert after.shape == before.shape
    # Previews (half size) while the sliders moved, then the full image once they rested.
    shown = d.execute_script("return shown")
    assert ["preview", 180, 210] in shown and shown[-1] == ["full", 360, 420], shown
    assert np.abs(after - before).mean() > 1.0  # the picture changed with the pose
    d.execute_script("window.scrollTo(0, 0)")
    d.save_screenshot(str(OUT / "web_page_posed.png"))
    # The camera sliders turn the view.
    yaw = d.find_element(*_by("#camera-yaw"))
    count = _renders(d)
    yaw.click()
    yaw.send_keys(*[Keys.ARROW_RIGHT] * 40)
    wait_for(lambda: _renders(d) > count and _idle(d), 60, "the render after turning the camera")
    assert np.abs(_image(d) - after).mean() > 1.0
    # The signer faced the camera: from 40 deg aside the page says the view was never seen.
    warnings = d.find_element(*_by("#pose-warnings"))
    assert warnings.is_displayed() and "camera is at yaw" in warnings.text, warnings.text
    assert not [e for e in d.get_log("browser") if e["level"] == "SEVERE"]


def test_animate_with_a_video_of_someone_else_and_play_it(site, avatar, other_signer_video):
    d = site.driver
    d.find_element(*_by("#driving-input")).send_keys(str(other_signer_video))
    d.find_element(*_by("#animate-panel summary")).click()
    d.find_element(*_by("#animate-fit-scale")).send_keys("0.1")
    assert d.find_element(*_by("#side-by-side")).is_selected()
    d.find_element(*_by("#animate-button")).click()
    wait_for(
        lambda: d.find_element(*_by("#animation-video")).get_attribute("data-animation-id"),
        400,
        "the animation to finish and load in the player",
        every=0.5,
    )
    metadata = (
        "const v = document.getElementById('animation-video');"
        "return v.readyState >= 1 ? [v.videoWidth, v.videoHeight, v.duration] : null"
    )
    width, height, duration = wait_for(lambda: d.execute_script(metadata), 30, "the video's metadata")
    assert (width, height) == (512, 256) and duration == pytest.approx(4.0, abs=0.6)  # 8 frames at 2 fps
    jobs = d.execute_script("return document.getElementById('jobs').textContent")
    assert "Animation with someone_else.mp4" in jobs
    assert d.find_element(*_by("#download-mp4")).is_enabled()
    video = d.find_element(*_by("#animation-video"))
    d.execute_script("arguments[0].scrollIntoView({block: 'center'})", video)
    d.save_screenshot(str(OUT / "web_page_animated.png"))


def test_eva_render_and_animate_on_the_service_avatar(site, avatar, tmp_path):
    from typer.testing import CliRunner

    from eva_engine.cli import app

    folder = site.data / "avatars" / avatar.id
    pose = {"joints": {"upperarm01.R": [0.0, 0.0, -1.2]}, "expression": {"mouthSmileLeft": 0.9}}
    runner = CliRunner()
    res = runner.invoke(
        app,
        [
            "render",
            str(folder),
            "--pose",
            json.dumps(pose),
            "--camera",
            "front_left",
            "--out",
            str(tmp_path / "pose.png"),
            "--width",
            "200",
            "--height",
            "240",
        ],
    )
    assert res.exit_code == 0, res.output
    image = np.asarray(Image.open(tmp_path / "pose.png").convert("RGB")).astype(int)
    assert image.shape == (240, 200, 3) and (np.abs(image - 255).sum(-1) > 40).mean() > 0.03
    res = runner.invoke(app, ["render", str(folder), "--pose", "frame:1", "--out", str(tmp_path / "f.png")])
    assert res.exit_code == 0, res.output
    assert Image.open(tmp_path / "f.png").size == (256, 256)  # the training frame's size
    motion = tmp_path / "wave.json"
    motion.write_text(json.dumps({"fps": 5, "poses": [{}, pose, {}, pose]}))
    res = runner.invoke(
        app,
        [
            "animate",
            str(folder),
            str(motion),
            "--out",
            str(tmp_path / "wave.mp4"),
            "--width",
            "96",
            "--height",
            "128",
        ],
    )
    assert res.exit_code == 0, res.output
    from eva_engine.data import read_video

    assert read_video(tmp_path / "wave.mp4").frames.shape == (4, 128, 96, 3)


def test_the_page_asks_for_the_key_once_and_sends_it(tmp_path):
    """A service with a key: the page asks for it, then every call carries it."""
    port = free_port()
    log = tmp_path / "serve.log"
    key_file = tmp_path / "api-key"
    key_file.write_text("s3cret-key-0123456789\n")  # from a file: a command line shows in `ps`
    args = [EVA, "serve", "--port", str(port), "--data-dir", str(tmp_path), "--api-key-file", str(key_file)]
    server = start_process(args, log)
    driver = profile = None
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as api:

            def healthy():
                try:
                    return api.get("/healthz").status_code == 200
                except httpx.TransportError:
                    assert server.poll() is None, log_tail(log)
                    return False

            wait_for(healthy, 90, "eva serve to answer /healthz")
        driver, profile = _browser()
        d = driver
        d.get(f"http://127.0.0.1:{port}/")
        dialog = "return document.getElementById('key-dialog').open"
        wait_for(lambda: d.execute_script(dialog), 30, "the page to ask for the key")
        d.find_element(*_by("#key-input")).send_keys("wrong")
        d.find_element(*_by("#key-form button")).click()
        wait_for(
            lambda: d.execute_script(dialog) and d.find_element(*_by("#key-error")).is_displayed(),
            30,
            "the page to say the key was refused",
        )
        d.find_element(*_by("#key-input")).send_keys("s3cret-key-0123456789")
        d.find_element(*_by("#key-form button")).click()
        empty = "return document.getElementById('avatars').textContent"
        wait_for(
            lambda: "No avatar yet" in d.execute_script(empty) and not d.execute_script(dialog),
            30,
            "the avatar list, fetched with the key",
        )
        assert d.execute_script("return sessionStorage.getItem('eva-api-key')") == "s3cret-key-0123456789"
        # The docs are behind the key, which a plain link cannot send: no link that answers 401.
        assert not d.find_element(*_by("a.docs")).is_displayed()
        OUT.mkdir(exist_ok=True)
        d.save_screenshot(str(OUT / "web_page_key.png"))
    finally:
        if driver is not None:
            driver.quit()
        if profile:
            shutil.rmtree(profile, ignore_errors=True)
        stop(server)
