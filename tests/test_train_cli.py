"""End to end on the synthetic benchmark's tiny preset: ``eva train`` -> avatar directory ->
``eva eval`` -> JSON with full / hand / face metrics; clear CLI errors (exit code 2)."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from eva_engine.avatar import read_avatar_meta
from eva_engine.cli import app
from eva_engine.synth import generate


@pytest.fixture(scope="module")
def dataset(anny_model, tmp_path_factory):
    return generate("controlled", "tiny", 0, tmp_path_factory.mktemp("synth") / "ds", model=anny_model)


def test_train_then_eval(dataset, tmp_path):
    runner = CliRunner()
    out = tmp_path / "avatar"
    args = ["--preset", "tiny", "--iterations", "30", "--method", "eva", "--set", "loss.lambda_ssim=0.05"]
    res = runner.invoke(app, ["train", str(dataset), "--out", str(out), *args])
    assert res.exit_code == 0, res.output
    assert (out / "avatar.ply").is_file() and (out / "avatar.safetensors").is_file()
    info = read_avatar_meta(out)
    assert info.iterations == 30 and info.method == "eva"
    assert info.train_config["strategy"]["name"] == "ContextAwareStrategy"
    assert info.train_config["loss"]["photometric"] == "confidence"
    assert info.train_config["loss"]["lambda_ssim"] == 0.05  # --set, after the method
    per_part = info.gaussians_per_part
    assert per_part["before"]["hand"] > 0 and sum(per_part["after"].values()) == info.num_gaussians
    assert info.num_gaussians > 0 and info.train_seconds > 0
    # Its quality report: the 3 held-out frames scored, printed and kept.
    assert info.quality["held_out"]["frames"] == 3 and 10 < info.quality["held_out"]["psnr"] < 60
    assert "held-out frames (3, poses it never trained on): PSNR" in res.output
    assert (
        info.quality["verdict"] in ("good", "fair", "poor")
        and f"quality: {info.quality['verdict']}" in res.output
    )
    report = tmp_path / "metrics.json"
    res = runner.invoke(app, ["eval", str(out), str(dataset), "--json", str(report)])
    assert res.exit_code == 0, res.output
    doc = json.loads(report.read_text())
    assert doc["split"] == "test_pose" and doc["num_frames"] == 3
    assert set(doc["regions"]) == {"full", "hand", "face"}
    full = doc["regions"]["full"]
    assert 10 < full["psnr"] < 60 and 0 < full["ssim"] <= 1
    assert 0 <= full["lpips_vgg"] < 1 and 0 <= full["lpips_alex"] < 1
    assert doc["regions"]["hand"]["crops"] >= doc["regions"]["hand"]["frames"] > 0
    assert "| Method | N-GS |" in doc["table"] and doc["protocol"] == "fitted poses"
    # the second protocol says so in its JSON and table
    res = runner.invoke(app, ["eval", str(out), str(dataset), "--refine-poses", "2", "--json", str(report)])
    assert res.exit_code == 0, res.output
    doc = json.loads(report.read_text())
    assert doc["protocol"].startswith("test-time refined poses (2 steps") and doc["protocol"] in doc["table"]


def test_cli_errors(tmp_path, dataset):
    runner = CliRunner()
    res = runner.invoke(app, ["train", str(tmp_path / "nope"), "--out", str(tmp_path / "a")])
    assert res.exit_code == 2 and "no dataset" in res.output
    res = runner.invoke(app, ["eval", str(tmp_path / "nope"), str(dataset)])
    assert res.exit_code == 2 and "no avatar directory" in res.output
    res = runner.invoke(app, ["train", str(dataset), "--out", str(tmp_path / "a"), "--preset", "huge"])
    assert res.exit_code == 2 and "unknown preset" in res.output
    res = runner.invoke(app, ["train", str(dataset), "--out", str(tmp_path / "a"), "--method", "gart"])
    assert res.exit_code == 2 and "unknown method" in res.output
    for bad in ("loss.nope=1", "loss.lpips_every=0", "iterations"):
        res = runner.invoke(app, ["train", str(dataset), "--out", str(tmp_path / "a"), "--set", bad])
        assert res.exit_code == 2 and "--set" in res.output, res.output
