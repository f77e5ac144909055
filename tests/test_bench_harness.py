"""The benchmarks' harness (``python -m bench``): one app over every benchmark, one result header
and writer, and the docs' generated tables current with the committed results."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from bench import cli, report, stats
from bench.machine import (
    SCHEMA_VERSION,
    command_line,
    local_path,
    portable_path,
    resumable,
    run_header,
    write_result,
)

ROOT = Path(__file__).resolve().parents[1]


def bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "bench", *args], cwd=ROOT, capture_output=True, text=True, timeout=120
    )


def test_every_benchmark_module_is_a_command_of_the_app():
    modules = {p.stem for p in (ROOT / "bench").glob("*.py")} - cli.LIBRARIES
    assert set(cli.benchmarks()) == modules
    listing = bench("--help")
    assert listing.returncode == 0, listing.stderr
    for name in ("align", "novel_pose", "report", "index"):
        assert name in listing.stdout


def test_a_benchmarks_own_options_pass_through():
    run = bench("stats_not_a_benchmark")
    assert run.returncode != 0
    run = bench("eval_compare", "--help")
    assert run.returncode == 0, run.stderr
    assert "--before" in run.stdout and run.stdout.startswith("usage: python -m bench eval_compare")


def test_the_results_index_is_current():
    run = bench("index", "--check")
    assert run.returncode == 0, run.stderr or run.stdout


def test_the_docs_generated_tables_are_current():
    run = bench("report", "--check")
    assert run.returncode == 0, run.stderr or run.stdout


def test_the_header_names_the_harness_command():
    assert (
        command_line(["/x/bench/__main__.py", "align", "--no-videos"]) == "python -m bench align --no-videos"
    )
    assert command_line(["/x/bench/train.py", "--preset", "fast"]) == "python -m bench.train --preset fast"
    forwarded = command_line(["python -m bench align", "--no-videos", "--out", "a b"])
    assert forwarded == "python -m bench align --no-videos --out 'a b'"
    head = run_header()
    assert head["schema"] == SCHEMA_VERSION
    assert {"date", "command", "commit", "machine"} <= set(head)


def test_the_writer_writes_json_and_markdown_and_refuses_a_list(tmp_path):
    doc = {**run_header(), "rows": [{"x": Path("a/b")}]}
    write_result(tmp_path, "r", doc, ["# R", "", "| x |"])
    assert json.loads((tmp_path / "r.json").read_text())["rows"] == [{"x": "a/b"}]
    assert (tmp_path / "r.md").read_text() == "# R\n\n| x |\n"
    with pytest.raises(TypeError):
        write_result(tmp_path, "bad", [doc], "x")


def test_only_the_code_that_made_a_results_runs_adds_to_them(tmp_path, monkeypatch):
    """A benchmark asked to add its missing runs to an existing result file (``--name`` of one
    that exists) refuses one made by other code: resumed, those runs would be written under this
    commit's header as this code's."""
    import bench.machine as machine
    from bench import time_to_quality

    monkeypatch.setattr(machine, "commit", lambda: "abc123")
    assert resumable({}, tmp_path / "r.json") == {}
    mine = {"commit": "abc123", "runs": [1]}
    assert resumable(mine, tmp_path / "r.json") == mine
    for made in ("0ld0ld", "abc123+dirty", None):
        with pytest.raises(SystemExit, match="holds runs made at"):
            resumable({"commit": made, "runs": []}, tmp_path / "r.json")
    # Before anything trains: the stale file is named and left as it was.
    stale = {**run_header(), "commit": "0ld0ld", "runs": [{"method": "eva", "seed": 0, "points": []}]}
    (tmp_path / "ttq.json").write_text(json.dumps(stale))
    with pytest.raises(SystemExit, match="ttq.json holds runs made at 0ld0ld"):
        time_to_quality.main(["--seeds", "0", "--methods", "eva", "--name", "ttq", "--out", str(tmp_path)])
    assert json.loads((tmp_path / "ttq.json").read_text()) == stale


def test_a_report_block_is_rewritten_and_an_unknown_one_refused(tmp_path):
    results = ROOT / "bench" / "results"
    text = "before\n<!-- bench report: paper_regime -->\nold table\n<!-- /bench report -->\nafter\n"
    new = report.render(text, results)
    assert new.startswith(
        "before\n<!-- bench report: paper_regime -->\n| | full | hand | face | N-GS | seeds |"
    )
    assert new.endswith("<!-- /bench report -->\nafter\n")
    assert report.render(new, results) == new
    with pytest.raises(KeyError, match="unknown bench report section"):
        report.render("<!-- bench report: nope -->\n<!-- /bench report -->\n", results)


def test_a_figure_in_a_sentence_is_rewritten_in_place_and_a_stale_doc_is_flagged(tmp_path):
    results = ROOT / "bench" / "results"
    text = "cuts it by <!-- bench figure: novel_pose.view.full.cut -->99%<!-- /bench figure --> in view.\n"
    new = report.render(text, results)
    assert new.startswith("cuts it by <!-- bench figure: novel_pose.view.full.cut -->")
    assert new.endswith("%<!-- /bench figure --> in view.\n") and "99%" not in new
    assert report.render(new, results) == new
    doc = tmp_path / "docs" / "a.md"
    doc.parent.mkdir()
    doc.write_text(text)
    assert report.run(check=True, root=tmp_path, results=results) == 1
    assert doc.read_text() == text  # --check leaves the doc alone
    assert report.run(root=tmp_path, results=results) == 0 and doc.read_text() == new
    with pytest.raises(KeyError, match="unknown bench figure"):
        report.render("<!-- bench figure: nope -->1<!-- /bench figure -->", results)
    # A paired gap read from an eval_compare file by its path and row.
    gap = "<!-- bench figure: eval_gap/expressions/colour_rate/eval_seated_lr3ev/full.psnr -->"
    assert report.render(f"{gap}x<!-- /bench figure -->", results).endswith("%<!-- /bench figure -->")
    with pytest.raises(KeyError, match="has no row"):
        report.render(gap.replace("full.psnr", "full.nope") + "x<!-- /bench figure -->", results)


def test_a_value_figure_reads_one_number_of_a_result_by_its_keys(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "r.json").write_text(json.dumps({"runs": [{"mm": 2.9493}, {"gap": -0.0123}]}))
    figure = "<!-- bench figure: value/a/r/runs/{} -->x<!-- /bench figure -->"
    assert report.render(figure.format("0/mm@2"), tmp_path).endswith("-->2.95<!-- /bench figure -->")
    assert "−1.2%<" in report.render(figure.format("1/gap@1x100%"), tmp_path)  # a true minus sign
    assert "-->+295<" in report.render(figure.format("0/mm@0+x100"), tmp_path)
    for bad, reason in (("2/mm@2", "has no"), ("0/mm", "is not"), ("0/nope@1", "has no")):
        with pytest.raises(KeyError, match=reason):
            report.render(figure.format(bad), tmp_path)
    with pytest.raises(KeyError, match="names no result file"):
        report.render("<!-- bench figure: value/b/r/x@1 -->x<!-- /bench figure -->", tmp_path)
    # A key that holds a slash (train.json's "<dataset>/<preset>@<label>"), thousands separated.
    # "<dataset>/<preset>" is a key of its own beside "<dataset>/<preset>/<method>@<label>".
    (tmp_path / "t.json").write_text(
        json.dumps({"set-0/fast": {"n": 1.0}, "set-0/fast/eva@thin": {"n": 43498.0}})
    )
    figure = "<!-- bench figure: value/t/set-0/fast{}/n@0, -->x<!-- /bench figure -->"
    assert "-->43,498<" in report.render(figure.format("/eva@thin"), tmp_path)
    assert "-->1<" in report.render(figure.format(""), tmp_path)


def test_a_value_figure_with_a_star_is_the_range_of_every_item_there(tmp_path):
    runs = {"runs": [{"s": 9.81, "gap": 2.5}, {"s": 9.02, "gap": -0.9}, {"s": 9.4, "gap": 0.1}]}
    (tmp_path / "r.json").write_text(json.dumps(runs | {"by": {"a": {"s": 3.0}, "b": {"s": 3.04}}}))
    figure = "<!-- bench figure: value/r/{} -->x<!-- /bench figure -->"
    assert "-->9.0–9.8<" in report.render(figure.format("runs/*/s@1"), tmp_path)
    assert "-->−0.9 to +2.5<" in report.render(figure.format("runs/*/gap@1+"), tmp_path)  # signed
    assert "-->3.0<" in report.render(figure.format("by/*/s@1"), tmp_path)  # one as printed
    assert "-->3.0<" in report.render(figure.format("by/a*/s@1"), tmp_path)  # the keys it matches
    (tmp_path / "k.json").write_text(json.dumps({"steps": {"pip install": 34.04}}))
    spaced = "<!-- bench figure: value/k/steps/pip_install@1 -->x<!-- /bench figure -->"
    assert "-->34.0<" in report.render(spaced, tmp_path)  # "_" for a key's space
    (tmp_path / "set").mkdir()
    for run, p50 in enumerate((27.8, 27.4, 28.04)):
        (tmp_path / "set" / f"run{run + 1}.json").write_text(json.dumps({"rows": [{"p50": p50}]}))
    runs = "<!-- bench figure: value/set/run*/rows/0/p50@1 -->x<!-- /bench figure -->"
    assert "-->27.4–28.0<" in report.render(runs, tmp_path)  # over files
    for bad, reason in (("runs/*/nope@1", "has no"), ("runs/0/s/*@1", "nothing under")):
        with pytest.raises(KeyError, match=reason):
            report.render(figure.format(bad), tmp_path)


def test_change_and_ratio_figures_compare_two_numbers_of_the_results(tmp_path):
    runs = [{"lpips": 0.1647, "iou": [0.8, 0.9], "s": 683.0}, {"lpips": 0.1691, "iou": [0.84], "s": 921.0}]
    (tmp_path / "levers.json").write_text(json.dumps({"runs": runs}))
    (tmp_path / "other.json").write_text(json.dumps({"lpips": 0.1573}))

    def figure(name: str) -> str:
        return report.render(f"<!-- bench figure: {name} -->x<!-- /bench figure -->", tmp_path)

    assert "-->+2.7%<" in figure("change/levers/runs/1/lpips~levers/runs/0/lpips@1")
    assert "-->−4.5%<" in figure("change/other/lpips~levers/runs/0/lpips@1")  # across files
    assert "-->1.35<" in figure("ratio/levers/runs/1/s~levers/runs/0/s@2")
    assert "-->+4.4<" in figure("difference/levers/runs/1/lpips~levers/runs/0/lpips@1x1000")
    assert "-->0.850<" in figure("value/levers/runs/0/iou/mean@3")  # a list summed up
    assert "-->166.9 ± 3.1<" in figure("stat/levers/runs/*/lpips@1x1000")  # mean ± std over runs
    with pytest.raises(KeyError, match="not a spread"):
        figure("stat/levers/runs/0/lpips@1")
    assert "-->0.80–0.84<" in figure("value/levers/runs/*/iou/min@2")
    with pytest.raises(KeyError, match="2 numbers, not one"):
        figure("change/levers/runs/*/lpips~other/lpips@1")
    with pytest.raises(KeyError, match="is not"):
        figure("ratio/levers/runs/1/s@2")


def test_a_paired_gap_against_zero_has_no_verdict_and_equal_zeros_no_gap():
    """A share that is zero in the baseline (holes, debris) gives no relative gap to judge; two
    zeros are no change. Neither raises."""
    verdict, gaps = stats.compare_paired([0.1, 0.2], [0.0, 0.0], lower_is_better=True)
    assert verdict == "no difference" and gaps["std"] == float("inf")
    verdict, gaps = stats.compare_paired([0.0, 0.0], [0.0, 0.0], lower_is_better=True)
    assert verdict == "no difference" and (gaps["mean"], gaps["std"]) == (0.0, 0.0)


def test_a_paper_gap_figure_pairs_two_methods_of_one_or_two_files_by_seed(tmp_path):
    def doc(*lpips_by_seed: float) -> dict:
        runs = [{"seed": s, "full": {"lpips_vgg": v, "psnr": 20.0 + v}} for s, v in enumerate(lpips_by_seed)]
        return {
            "date": "d",
            "machine": "m",
            "methods": {"eva": {"runs": runs}, "3dgs+body": {"runs": runs[:2]}},
        }

    (tmp_path / "base.json").write_text(json.dumps(doc(0.10, 0.20, 0.30)))
    (tmp_path / "thin_seed0.json").write_text(json.dumps(doc(0.09, 0.18)))  # -10% on each seed
    figure = "<!-- bench figure: paper_gap/{} -->x<!-- /bench figure -->"
    assert "-->−10.0 ± 0.0% (better)<" in report.render(figure.format("thin@eva/base@eva/full"), tmp_path)
    assert "-->+0.0 ± 0.0% (no difference)<" in report.render(
        figure.format("base@eva/base@3dgs+body/full"), tmp_path
    )
    with pytest.raises(KeyError, match="is not"):
        report.render(figure.format("thin/base@eva/full"), tmp_path)


def test_a_novel_pose_gap_figure_pairs_two_rows_by_seed(tmp_path):
    def split(lpips: float, psnr: float) -> dict:
        region = {"lpips_vgg": lpips, "psnr": psnr}
        stat = {"mean": 0.0, "std": 0.0, "n": 2}
        return {
            "full": region,
            "hand": region,
            "face": region,
            "arm": region,
            "debris": 0.01,
            "holes": 0.0,
        }, {
            "full": {"lpips_vgg": stat},
            "hand": {},
            "face": {},
            "arm": {},
            "debris": stat,
            "holes": stat,
        }

    def row(*by_seed: tuple[float, float]) -> dict:
        runs = [{"seed": s, "splits": {k: split(*v)[0] for k in splits}} for s, v in enumerate(by_seed)]
        return {"seeds": [0, 1], "splits": {k: split(0.1, 20.0)[1] for k in splits}, "runs": runs}

    splits = report.NOVEL_POSE_SPLITS

    doc = {"date": "d", "machine": "m", "methods": {"base": row((0.10, 20.0), (0.20, 22.0))}}
    doc["methods"]["new"] = row((0.11, 19.8), (0.22, 21.78))  # LPIPS +10% and PSNR -1% on each seed
    (tmp_path / "np.json").write_text(json.dumps(doc))
    figure = "<!-- bench figure: novel_pose_gap/np/new/base/view.{} -->x<!-- /bench figure -->"
    assert "-->+10.0 ± 0.0%, worse<" in report.render(figure.format("full"), tmp_path)
    assert "-->−1.0 ± 0.0%, worse<" in report.render(figure.format("hand.psnr"), tmp_path)
    # The spread of a row's split means, and its ratio to another row's.
    doc = json.loads(json.dumps(doc))  # the rows share their stat dicts
    for k, name in enumerate(splits):
        doc["methods"]["new"]["splits"][name]["debris"]["mean"] = 0.001 * (k + 1)
        for row, lpips in (("base", 0.1), ("new", 0.1 * (k + 2))):
            doc["methods"][row]["splits"][name]["full"]["lpips_vgg"]["mean"] = lpips
    (tmp_path / "np.json").write_text(json.dumps(doc))
    figure = "<!-- bench figure: novel_pose_{} -->x<!-- /bench figure -->"
    assert "-->0.1-0.4%<" in report.render(figure.format("span/np/new/debris"), tmp_path)
    assert f"-->2.0-{len(splits) + 1:.1f}×<" in report.render(
        figure.format("ratio/np/new/base/full"), tmp_path
    )


def test_novel_pose_angle_and_novelty_figures_bin_the_scored_frames(tmp_path):
    def frame(view_deg: float, yaw_deg: float, pose_deg: float, lpips: float) -> dict:
        return {
            "view_deg": view_deg,
            "yaw_deg": yaw_deg,
            "pose_deg": pose_deg,
            "lpips_vgg": lpips,
            "debris": 0.02,
            "holes": 0.0,
        }

    near = {"per_frame": {"0": frame(0, 0, 15, 0.03), "1": frame(0, 5, 25, 0.05)}}
    view = {"per_frame": {"0": frame(35, 40, 0, 0.06), "1": frame(70, 75, 0, 0.12)}}
    splits = {"near": near, "far": near, "view": view, "far_view": view}
    doc = {
        "config": {"train_yaw_deg_by_seed": {"0": [-29.0, 29.0]}},
        "methods": {"thin": {"runs": [{"seed": 0, "splits": splits}]}},
    }
    (tmp_path / "np.json").write_text(json.dumps(doc))
    figure = "<!-- bench figure: novel_pose_{} -->x<!-- /bench figure -->"
    assert "-->60.0<" in report.render(figure.format("angle/np/thin/35.lpips_vgg"), tmp_path)
    assert "-->2.00%<" in report.render(figure.format("angle/np/thin/70.debris"), tmp_path)
    assert "-->60.0<" in report.render(
        figure.format("novelty/np/thin/yaw_beyond/10.lpips_vgg"), tmp_path
    )  # 11° beyond
    assert "-->50.0<" in report.render(figure.format("novelty/np/thin/pose/20.lpips_vgg"), tmp_path)
    with pytest.raises(KeyError, match="no pose bin"):
        report.render(figure.format("novelty/np/thin/pose/40.lpips_vgg"), tmp_path)


def test_a_result_of_another_shape_fails_loudly(tmp_path):
    (tmp_path / "service.json").write_text(json.dumps({"date": "d", "machine": "m", "rows": [{"size": 1}]}))
    with pytest.raises(ValueError):
        report.service_latency(tmp_path)


def test_result_files_name_paths_the_same_on_every_machine(tmp_path, monkeypatch):
    data = tmp_path / "elsewhere"
    monkeypatch.setenv("EVA_DATA_DIR", str(data))
    assert portable_path(ROOT / "bench" / "results") == "bench/results"
    assert portable_path(data / "synthetic" / "wild") == "$EVA_DATA_DIR/synthetic/wild"
    for name in ("bench/results", "$EVA_DATA_DIR/synthetic/wild"):
        assert portable_path(local_path(name)) == name
    doc = {**run_header(), "dataset": str(data / "ds"), "runs": [{"avatar": data / "a"}], "url": "/avatars/x"}
    write_result(tmp_path / "out", "r", doc, "# r")
    written = json.loads((tmp_path / "out" / "r.json").read_text())
    assert written["dataset"] == "$EVA_DATA_DIR/ds"
    assert written["runs"] == [{"avatar": "$EVA_DATA_DIR/a"}]
    assert written["url"] == "/avatars/x"


def test_a_results_command_names_paths_as_its_files_do(tmp_path, monkeypatch):
    data = tmp_path / "elsewhere"
    monkeypatch.setenv("EVA_DATA_DIR", str(data))
    beside = ROOT.parent / "shared" / "reference" / "videos" / "clip.mp4"
    line = command_line(
        ["python -m bench real_videos", str(beside), f"--dataset={data / 'ds'}", "--out", str(ROOT / "out")]
    )
    assert line == (  # shlex quotes the "$"
        "python -m bench real_videos ../shared/reference/videos/clip.mp4 "
        "'--dataset=$EVA_DATA_DIR/ds' --out out"
    )
    assert local_path("../shared/reference") == ROOT / "../shared/reference"


# A committed result names no folder of the machine that ran it (``portable_path``); the logs
# kept beside some results are the verbatim output of a run and keep its paths.
MACHINE_PATH = re.compile(r"(?<![\w$.~-])/(?:work|tmp|root|home|Users|private|var/folders)/")


def test_committed_results_name_no_folder_of_the_machine_that_ran_them():
    try:
        listed = subprocess.run(
            ["git", "ls-files", "bench/results"], cwd=ROOT, capture_output=True, text=True
        )
    except OSError:
        listed = None
    if listed is None or listed.returncode != 0:
        pytest.skip("not a git checkout: the committed results are not known")
    offenders = []
    for name in listed.stdout.split():
        if Path(name).suffix not in {".json", ".md", ".txt", ".csv", ".py", ".patch"}:
            continue
        text = (ROOT / name).read_text(errors="replace")
        offenders += [f"{name}: {m.group(0)}" for m in MACHINE_PATH.finditer(text)][:1]
    assert not offenders, offenders[:10]


def test_the_test_suite_benchmark_reads_pytests_summary_line():
    from bench.test_suite import pytest_summary

    out = "ruff ok\n.....\n===== 867 passed, 1 skipped, 2 warnings in 231.61s (0:03:51) =====\n"
    assert pytest_summary(out) == ({"passed": 867, "skipped": 1, "warnings": 2}, 231.61)
    assert pytest_summary("3 passed in 0.5s") == ({"passed": 3}, 0.5)
    failed = "28.04s call     tests/test_demo.py::test_x\n== 1 failed, 875 passed in 220.10s (0:03:40) ==\n"
    assert pytest_summary(failed) == ({"failed": 1, "passed": 875}, 220.1)
    assert pytest_summary("make: *** [Makefile:44: test] Error 1") == ({}, None)


def test_hard_inputs_pairs_a_variant_with_its_plain_runs(tmp_path):
    """`bench hard_inputs --compare-variant`: each variant run against the plain run of its case,
    seed and bound; the main report leaves variants out."""
    from bench import hard_inputs

    def run(seed: int, lpips: float, variant: str | None = None, cap: float | None = 10.0) -> None:
        r = {"case": "blur", "seed": seed, "max_scale_cm": cap, "refusal_case": False, "refused": None}
        if variant:
            r["variant"] = variant
        r["truth"] = {"lpips_vgg": lpips, "psnr": 20.0, "silhouette_iou": 0.9}
        r["quality"] = {"verdict": "good", "held_out": {"lpips_vgg": lpips - 0.01}}
        folder = tmp_path / "work" / hard_inputs.run_name(r)
        folder.mkdir(parents=True)
        (folder / "result.json").write_text(json.dumps(r))

    for seed, (plain, variant) in enumerate([(0.110, 0.100), (0.180, 0.171), (0.120, 0.110)]):
        run(seed, plain)
        run(seed, variant, "grad")
    run(3, 0.1, "grad")  # no plain run: left out
    assert hard_inputs.run_name({"case": "blur", "seed": 2, "max_scale_cm": 10.0, "variant": "grad"}) == (
        "blur_cap10_grad_s2"
    )
    out = tmp_path / "out"
    hard_inputs.main(["--work", str(tmp_path / "work"), "--compare-variant", "grad", "--out", str(out)])
    doc = json.loads((out / "hard_inputs_grad.json").read_text())
    assert len(doc["runs"]) == 3
    lpips = doc["paired"]["blur_cap10"]["truth LPIPS-VGG ×1000"]
    assert lpips["verdict"] == "better" and lpips["seeds"] == 3 and lpips["mean"] < -5
    with pytest.raises(SystemExit, match="no runs of variant"):
        hard_inputs.main(["--work", str(tmp_path / "work"), "--compare-variant", "other", "--out", str(out)])


def test_an_expr_gap_figure_reads_a_paired_row_in_its_own_units(tmp_path):
    stat = {"mean": 0.0, "std": 0.0, "n": 3}

    def row(measure: str, mean: float, std: float, unit: str) -> dict:
        gap = {"mean": mean, "std": std, "n": 3}
        return {
            "measure": measure,
            "before": stat,
            "after": stat,
            "gap": gap,
            "gap_unit": unit,
            "verdict": "-",
        }

    rows = [row("eyes_r", 0.123, 0.04, "absolute"), row("lpips_vgg", -11.14, 0.41, "%")]
    (tmp_path / "c.json").write_text(json.dumps({"date": "d", "rows": rows}))
    figure = "<!-- bench figure: expr_gap/c/{} -->x<!-- /bench figure -->"
    assert "-->+0.12 ± 0.04<" in report.render(figure.format("eyes_r"), tmp_path)
    assert "-->−11.1 ± 0.4%<" in report.render(figure.format("lpips_vgg"), tmp_path)
    with pytest.raises(KeyError, match="has no row"):
        report.render(figure.format("mouth_r"), tmp_path)
