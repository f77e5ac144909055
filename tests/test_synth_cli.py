"""`eva synth`: writes a loadable dataset; bad input is a usage error (exit code 2), never a
crash, and an existing folder is never replaced without --overwrite."""

from __future__ import annotations

from typer.testing import CliRunner

from eva_engine.cli import app
from eva_engine.data import load_dataset


def test_synth_writes_a_dataset(tmp_path):
    out = tmp_path / "ds"
    result = CliRunner().invoke(
        app, ["synth", "--preset", "controlled", "--size", "tiny", "--seed", "2", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    ds = load_dataset(out)
    assert ds.meta.extra["preset"] == "controlled" and ds.meta.extra["seed"] == 2 and len(ds) == 18
    again = CliRunner().invoke(app, ["synth", "--size", "tiny", "--out", str(out)])
    assert again.exit_code == 2 and "already exists" in again.output


def test_synth_rejects_bad_input(tmp_path):
    runner = CliRunner()
    for args in (["--preset", "studio"], ["--size", "huge"], ["--seed", "-1"], ["--seed", "x"]):
        result = runner.invoke(app, ["synth", *args, "--out", str(tmp_path / "x")])
        assert result.exit_code == 2, (args, result.output)
    (tmp_path / "file").write_text("not a folder")
    result = runner.invoke(app, ["synth", "--out", str(tmp_path / "file")])
    assert result.exit_code == 2 and "not a folder" in result.output
    assert not (tmp_path / "x").exists()
