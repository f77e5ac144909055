"""``python -m bench report``: the tables the docs include, written from the result files.

A doc includes a table between two markers; everything between them is this module's output:

    <!-- bench report: paper_tables -->
    | | full | hand | face | N-GS |
    ...
    <!-- /bench report -->

A figure in a sentence is written the same way, inline, by a function of ``FIGURES`` (or, named
``<family>/<argument>``, of ``FIGURE_FAMILIES``, e.g. ``eval_gap/<result>/<region>.<metric>``;
``value/<result>/<key>/...@<digits>``, one number of a result file, or with ``*`` the range of
several; ``stat/...``, their mean ± std; ``change/<a>~<b>@<digits>``, ``difference/...`` and
``ratio/...``, two numbers compared):

    side views by <!-- bench figure: novel_pose.view.full.cut -->22%<!-- /bench figure -->

``report --check`` fails when a doc's table or figure is not what the committed results give (a
test runs it), so neither can drift from its file. Each section reads its result through
a pydantic model of the fields it uses: a result whose shape changed fails loudly here, not as a
wrong number in the docs.
"""

from __future__ import annotations

import fnmatch
import json
import re
import statistics
from collections.abc import Callable
from pathlib import Path
from typing import Generic, NamedTuple, TypeVar

from pydantic import BaseModel, ConfigDict

from bench.novel_pose_tables import by_novelty, view_breakdown
from bench.seed_results import load_seeds, runs_by_seed, union_of_runs
from bench.stats import compare_paired, fmt, mean_std, zero_crossing

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
DOCS = ("README.md", "docs/*.md")
FIGURE = re.compile(
    r"(<!-- bench figure: (?P<name>[\w./@%,+*~'-]+) -->)(?P<body>.*?)(<!-- /bench figure -->)"
)
BLOCK = re.compile(r"(<!-- bench report: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /bench report -->)", re.S)


# ----------------------------------------------------------------------------- result shapes


class _Loose(BaseModel):
    model_config = ConfigDict(extra="ignore")


class _Run(_Loose):
    """A result file's run header: when and at which commit (older results recorded none)."""

    date: str
    commit: str | None = None


class Stat(_Loose):
    """``bench.stats.mean_std``: a mean over seeds."""

    mean: float
    std: float
    n: int


class MethodSummary(_Loose):
    """One method of ``paper_tables.json`` / ``paper_regime.json`` over its seeds."""

    seeds: list[int]
    n_gaussians: Stat
    full: dict[str, Stat]
    hand: dict[str, Stat]
    face: dict[str, Stat]


class PaperTables(_Loose):
    """``bench.paper_tables``' merged result (``--merge``)."""

    date: str
    command: str
    methods: dict[str, MethodSummary]


class LatencyRow(_Loose):
    size: int
    format: str
    varies: str
    clients: int
    requests: int
    p50_ms: float
    p95_ms: float
    throughput_rps: float


class ServiceLatency(_Run):
    """``bench.serving latency``'s result."""

    machine: str
    rows: list[LatencyRow]


V = TypeVar("V", float, Stat)


class NovelPoseSplit(_Loose, Generic[V]):
    """One split of ``novel_pose.json``, with ``V`` a seed's value (float) or a mean over seeds
    (``Stat``): per region each metric; debris and holes as fractions of the alpha mass and of
    the person's pixels."""

    full: dict[str, V]
    hand: dict[str, V]
    face: dict[str, V]
    arm: dict[str, V]
    debris: V
    holes: V
    closeup: dict[str, V] | None = None
    """The head through the face close-ups' cameras (datasets that have them): psnr, lpips_vgg."""


class NovelPoseRun(_Loose):
    seed: int
    splits: dict[str, NovelPoseSplit[float]]


class NovelPoseRow(_Loose):
    seeds: list[int]
    splits: dict[str, NovelPoseSplit[Stat]]
    runs: list[NovelPoseRun]


class NovelPose(_Run):
    """``bench.novel_pose``'s merged result: one row per training variant."""

    methods: dict[str, NovelPoseRow]


def load(model: type[BaseModel], name: str, results: Path) -> BaseModel:
    return model.model_validate_json((results / f"{name}.json").read_text())


def load_each(model: type[BaseModel], pattern: str, results: Path) -> list[tuple[str, BaseModel]]:
    """(name, parsed) of every result file whose name (under ``results``, without ``.json``)
    matches the glob ``pattern``, in name order."""
    paths = sorted(results.glob(f"{pattern}.json"))
    names = [p.relative_to(results).with_suffix("").as_posix() for p in paths]
    return [(name, load(model, name, results)) for name in names]


# ----------------------------------------------------------------------------- sections


def _mean_std(stat: Stat, scale: float = 1e3, digits: int = 1) -> str:
    if stat.n < 2:
        return f"{stat.mean * scale:.{digits}f}"
    return f"{stat.mean * scale:.{digits}f} ± {stat.std * scale:.{digits}f}"


def _seeds(seeds: list[int]) -> str:
    seeds = sorted(seeds)
    contiguous = seeds == list(range(seeds[0], seeds[-1] + 1))
    if len(seeds) > 1 and contiguous:
        return f"{seeds[0]}-{seeds[-1]}"
    return ", ".join(map(str, seeds))


def _lpips_table(doc: PaperTables, rows: dict[str, str], seeds_column: bool) -> list[str]:
    """LPIPS-VGG ×1000 (full, hand, face) and the Gaussian count, one row per method in ``rows``
    (method -> its label), in that order."""
    head = "| | full | hand | face | N-GS |" + (" seeds |" if seeds_column else "")
    rule = "|---|---:|---:|---:|---:|" + ("---|" if seeds_column else "")
    lines = [head, rule]
    for method, label in rows.items():
        m = doc.methods[method]
        cells = [
            _mean_std(m.full["lpips_vgg"]),
            _mean_std(m.hand["lpips_vgg"]),
            _mean_std(m.face["lpips_vgg"]),
        ]
        cells.append(f"{m.n_gaussians.mean:,.0f}")
        if seeds_column:
            cells.append(_seeds(m.seeds))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def paper_tables(results: Path) -> list[str]:
    """The paper's Tables 1-2 on the synthetic ``controlled`` benchmark (``paper_tables.json``)."""
    doc = load(PaperTables, "paper_tables", results)
    rows = {
        "3dgs+body": "3dgs+body (3DGS density control, L1 + D-SSIM)",
        "eva": "eva (CADC + CL + SSIM/LPIPS-Alex terms)",
        "eva-no-cl": "eva-no-cl (CADC, no CL)",
        "eva-no-cadc": "eva-no-cadc (CL, no CADC)",
        "eva-no-cadc-no-cl": "eva-no-cadc-no-cl (the full objective alone)",
        "gauhuman+body": "gauhuman+body (`docs/baselines.md`)",
        "gart+body": "gart+body (`docs/baselines.md`)",
    }
    return _lpips_table(doc, rows, seeds_column=False)


def baselines(results: Path) -> list[str]:
    """The four methods and EVA's ablation without its contributions on the synthetic benchmark
    (``paper_tables.json``; docs/baselines.md, "Results")."""
    doc = load(PaperTables, "paper_tables", results)
    names = ("3dgs+body", "gart+body", "gauhuman+body", "eva-no-cadc-no-cl", "eva")
    return _lpips_table(doc, {name: name for name in names}, seeds_column=False)


def baselines_real(results: Path) -> list[str]:
    """Every method on the two full-body reference videos (``real_videos.json``): LPIPS-VGG ×1000
    full / hand / face (docs/baselines.md, "Results")."""
    doc = load(RealVideos, "real_videos", results)
    videos = list(doc.videos)
    head = "| | " + " | ".join(v.removesuffix(".mp4") for v in videos) + " |"
    lines = [head, "|---|" + "---|" * len(videos)]
    for method in doc.videos[videos[0]].methods:
        cells = []
        for video in videos:
            m = doc.videos[video].methods[method]
            cells.append(" / ".join(f"{1e3 * r['lpips_vgg']:.1f}" for r in (m.full, m.hand, m.face)))
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return lines


REAL_VIDEO_HANDS = {"gesturing": "real_videos_hands_gesturing_s*", "seated": "real_videos_hands_s*"}
"""The hand-rich videos' runs in ``real_videos_hands/`` (one file per seed), by the docs' label."""
REAL_VIDEO_HANDS_LABELS = {"eva-official": "eva-official (trained on the metric; scored on black)"}


def region_lpips(runs: list[RealVideoMethod]) -> list[str]:
    """Full, hand and face LPIPS-VGG ×1000 over ``runs`` (one method's, e.g. one per seed)."""
    return [
        _mean_std(Stat(**mean_std([getattr(m, region)["lpips_vgg"] for m in runs])))
        for region in ("full", "hand", "face")
    ]


def real_video_hands(results: Path) -> list[str]:
    """Each method on the two LatentSync videos over the seeds run (``real_videos_hands/``):
    LPIPS-VGG ×1000 full / hand / face, Gaussians and training seconds (docs/eva-contributions.md,
    "Hand-rich real video")."""
    lines = [
        "| video | method | seeds | full | hand | face | N-GS | train (s) |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for label, pattern in REAL_VIDEO_HANDS.items():
        runs = {}  # method -> [(seed, RealVideoMethod)]
        for name, doc in load_each(RealVideos, f"real_videos_hands/{pattern}", results):
            seed = int(name.rsplit("_s", 1)[1])
            (video,) = doc.videos.values()
            for method, m in video.methods.items():
                runs.setdefault(method, []).append((seed, m))
        for method, seeded in runs.items():
            ms = [m for _, m in seeded]
            cells = region_lpips(ms)
            cells.append(f"{sum(m.n_gaussians for m in ms) / len(ms):,.0f}")
            cells.append(f"{sum(m.train_seconds for m in ms) / len(ms):.0f}")
            seeds = _seeds([seed for seed, _ in seeded])
            name = REAL_VIDEO_HANDS_LABELS.get(method, method)
            lines.append(f"| {label} | {name} | {seeds} | " + " | ".join(cells) + " |")
    return lines


class MetricChange(_Loose):
    """One metric of ``bench.real_videos_compare``: before and after over the seeds, the per-seed
    relative gap (%) and its verdict."""

    before: Stat
    after: Stat
    gap_pct: Stat
    verdict: str


class RealVideosCompare(_Run):
    """``bench.real_videos_compare``'s result: video -> region -> metric -> its change."""

    comparison: dict[str, dict[str, dict[str, MetricChange]]]


def real_videos_change(
    name: str, psnr: bool = False, labels: tuple[str, str] = ("before", "after")
) -> Callable[[Path], list[str]]:
    """The section of one ``real_videos_compare`` result ``name``: per video and region,
    LPIPS-VGG ×1000 before, after (the columns' ``labels``) and the paired change (with ``psnr``,
    PSNR's too)."""

    def section(results: Path) -> list[str]:
        doc = load(RealVideosCompare, name, results)
        if psnr:
            lines = [
                "| video | region | LPIPS-VGG before | after | change | PSNR before | after | change |",
                "|---|---|---:|---:|---|---:|---:|---|",
            ]
        else:
            lines = [f"| video | region | {labels[0]} | {labels[1]} | change |", "|---|---|---:|---:|---|"]
        for video, regions in doc.comparison.items():
            for region, metrics in regions.items():
                v = metrics["lpips_vgg"]
                gap = f"{_percent_gap(v.gap_pct.mean, v.gap_pct.std)} ({v.verdict})"
                cells = [_mean_std(v.before), _mean_std(v.after), gap]
                if psnr:
                    p = metrics["psnr"]
                    cells += [f"{p.before.mean:.2f}", f"{p.after.mean:.2f}", p.verdict]
                lines.append(f"| {video.removesuffix('.mp4')} | {region} | " + " | ".join(cells) + " |")
        return lines

    return section


class OpeningChange(_Loose):
    """One row of ``bench.expressions_compare``: a measure of issue 39 before and after, paired."""

    measure: str
    before: Stat
    after: Stat
    gap: Stat
    gap_unit: str
    verdict: str

    @property
    def relative(self) -> bool:
        """The gap is in % of before (LPIPS, PSNR), not in the measure's own units."""
        return self.gap_unit in ("%", "percent")


class OpeningsPaired(_Run):
    """``bench.expressions_compare``'s result."""

    rows: list[OpeningChange]


class EvalChange(_Loose):
    """One row of an ``eva eval`` comparison: a region's metric before and after, paired."""

    region: str
    metric: str
    before: Stat
    after: Stat
    gap_percent: Stat
    verdict: str


class EvalPaired(_Run):
    rows: list[EvalChange]


# (label, source, key): source "openings" reads ``OpeningsPaired`` rows by measure, "eval"
# ``EvalPaired`` rows by "region.metric"; LPIPS is shown ×1000.
OPENING_ROWS = (
    ("mouth r", "openings", "mouth_r"),
    ("mouth range", "openings", "mouth_range"),
    ("eyes r", "openings", "eyes_r"),
    ("eyes range", "openings", "eyes_range"),
)
# The same with the full ranges (max - min, ``Agreement.full_range_ratio``), which a blink's few
# closed test frames decide; comparisons written before them lack these rows.
OPENING_ROWS_FULL = (
    *OPENING_ROWS,
    ("mouth full range", "openings", "mouth_full_range"),
    ("eyes full range", "openings", "eyes_full_range"),
)


LPIPS_ROWS = (  # each region's held-out LPIPS-VGG from an ``eva eval`` comparison
    ("face LPIPS-VGG ×1000", "eval", "face.lpips_vgg"),
    ("full LPIPS-VGG ×1000", "eval", "full.lpips_vgg"),
    ("hand LPIPS-VGG ×1000", "eval", "hand.lpips_vgg"),
)


class PairedChange(NamedTuple):
    """One paired change of issue 39's comparisons, LPIPS ×1000: before and after over the seeds,
    the per-seed gap (in % where ``percent``) and its verdict."""

    before: Stat
    after: Stat
    gap: Stat
    verdict: str
    percent: bool


def _scaled(stat: Stat, scale: float) -> Stat:
    return Stat(mean=stat.mean * scale, std=stat.std * scale, n=stat.n)


def _paired_changes(openings: str, evals: str | None, results: Path) -> dict[str, dict[str, PairedChange]]:
    """The changes of one ``bench.expressions_compare`` result (``"openings"``, by measure; its
    LPIPS is ×1000 already) and one ``eva eval`` comparison (``"eval"``, by ``region.metric``;
    none without ``evals``)."""
    opened = load(OpeningsPaired, openings, results).rows
    evaluated = load(EvalPaired, evals, results).rows if evals else []
    return {
        "openings": {
            r.measure: PairedChange(r.before, r.after, r.gap, r.verdict, r.relative) for r in opened
        },
        "eval": {
            f"{r.region}.{r.metric}": PairedChange(
                _scaled(r.before, 1e3 if "lpips" in r.metric else 1.0),
                _scaled(r.after, 1e3 if "lpips" in r.metric else 1.0),
                r.gap_percent,
                r.verdict,
                True,
            )
            for r in evaluated
        },
    }


def _change(change: PairedChange, digits: int) -> list[str]:
    """The cells before | after | gap of a paired change; the gap alone says "no difference"."""
    before, after, gap, verdict, percent = change
    if verdict == "no difference":
        cell = verdict
    elif percent:
        places = 2 if gap.std < 0.1 else 1  # a small gap keeps its second decimal
        cell = f"{_signed(gap.mean, places)} ± {gap.std:.{places}f}%, {verdict}"
    else:
        cell = f"{_signed(gap.mean, 2)} ± {gap.std:.2f}, {verdict}"
    return [
        f"{before.mean:.{digits}f} ± {before.std:.{digits}f}",
        f"{after.mean:.{digits}f} ± {after.std:.{digits}f}",
        cell,
    ]


def face_changes(
    heading: str,
    columns: tuple[str, str],
    openings: str,
    evals: str | None,
    rows: tuple[tuple[str, str, str], ...],
    clips: tuple[str, ...] = ("gesturing", "seated"),
) -> Callable[[Path], list[str]]:
    """A section of issue 39's paired comparisons on the upper-body clips: per row, each clip's
    before ± std, after ± std and gap (``columns`` name before and after); ``openings`` and
    ``evals`` are result names with ``{clip}`` for the clip (``bench.expressions_compare`` and
    ``eva eval`` comparisons; no ``evals``: the rows read ``openings`` only). LPIPS is shown ×1000."""

    def section(results: Path) -> list[str]:
        found = {
            clip: _paired_changes(openings.format(clip=clip), evals and evals.format(clip=clip), results)
            for clip in clips
        }
        head = " | ".join(f"{clip}, {columns[0]} | {columns[1]} | gap" for clip in clips)
        lines = [f"| {heading} | {head} |", "|---|" + "---:|---:|---:|" * len(clips)]
        for label, source, key in rows:
            cells = []
            for clip in clips:
                cells += _change(found[clip][source][key], 1 if "lpips" in key else 2)
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        return lines

    return section


def clips_and_driving(
    name: str,
    columns: tuple[str, str],
    openings: str,
    evals: str,
    opening_rows: tuple[tuple[str, str, str], ...] = OPENING_ROWS,
) -> dict[str, Callable[[Path], list[str]]]:
    """The two sections of one paired comparison on the upper-body clips: ``name`` (both clips'
    openings, LPIPS-VGG and PSNR) and ``<name>_driving`` (the openings of the gesturing avatars
    driven by the seated clip's fit); arguments as :func:`face_changes`', ``opening_rows`` the
    openings' rows."""
    heading = "mean ± std, 3 seeds (gap: per seed)"
    rows = (
        *opening_rows,
        *LPIPS_ROWS,
        ("full PSNR", "eval", "full.psnr"),
        ("hand PSNR", "eval", "hand.psnr"),
    )
    return {
        name: face_changes(heading, columns, openings, evals, rows),
        f"{name}_driving": face_changes(heading, columns, openings, None, opening_rows, clips=("driving",)),
    }


def face_variants(
    openings: str,
    evals: str,
    variants: dict[str, str],
    rows: tuple[tuple[str, str, str], ...],
    clips: tuple[str, str] = ("gesturing", "seated"),
) -> Callable[[Path], list[str]]:
    """Several variants against one before on two clips, compactly: per row, the before's means
    (clip / clip), then per variant its means (openings) or paired gaps (image metrics) with the
    verdicts. ``openings`` / ``evals``: result names with ``{clip}`` and ``{variant}``;
    ``variants``: variant -> its column's label."""

    def section(results: Path) -> list[str]:
        found = {
            (variant, clip): _paired_changes(
                openings.format(clip=clip, variant=variant), evals.format(clip=clip, variant=variant), results
            )
            for variant in variants
            for clip in clips
        }
        pair = " / ".join(clips)
        lines = [
            f"| measure ({pair}) | before | " + " | ".join(variants.values()) + " |",
            "|---|" + "---|" * (1 + len(variants)),
        ]
        first = next(iter(variants))
        for label, source, key in rows:
            digits = 1 if "lpips" in key else 2
            cells = [" / ".join(f"{found[first, c][source][key].before.mean:.{digits}f}" for c in clips)]
            for variant in variants:
                got = [found[variant, c][source][key] for c in clips]
                if source == "openings":
                    values = " / ".join(f"{g.after.mean:.{digits}f}" for g in got)
                else:
                    values = " / ".join(_percent_gap(g.gap.mean, g.gap.std) for g in got)
                cells.append(f"{values} ({' / '.join(g.verdict for g in got)})")
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        return lines

    return section


def smoothing_stages(results: Path) -> list[str]:
    """The expression's time smoothing on and off, stage by stage (docs/alignment.md): the fit (one
    per clip, so seed 0's case), the render over the seeds, and ``eva eval``'s face and full
    LPIPS-VGG (``expressions/smoothing/``)."""
    folder = "expressions/smoothing"
    columns = {
        "gesturing, σ = 0.04 s": ("expressions_base", "eval_nosmooth", "before"),
        "gesturing, σ = 0": ("expressions_nosmooth", "eval_nosmooth", "after"),
        "seated, σ = 0.04 s": ("expressions_seated_base", "eval_nosmooth_seated", "before"),
        "seated, σ = 0": ("expressions_seated_nosmooth", "eval_nosmooth_seated", "after"),
    }
    cells: dict[str, list[str]] = {}
    for openings, evals, side in columns.values():
        cases = list(load(ExpressionsResult, f"{folder}/{openings}", results).cases.values())
        fitted = cases[0].stages["fitted"]
        render = [c.stages["render"] for c in cases]
        rows = {f"{r.region}.{r.metric}": r for r in load(EvalPaired, f"{folder}/{evals}", results).rows}
        column = {
            "fitted: mouth r / range over the target's": f"{fitted['mouth'].r:.2f} / "
            f"{fitted['mouth'].range_ratio:.2f}",
            "fitted: eyes r / range": f"{fitted['eyes'].r:.2f} / {fitted['eyes'].range_ratio:.2f}",
            "render: mouth r": _stat([r["mouth"].r for r in render], 2),
            "render: mouth range": _stat([r["mouth"].range_ratio for r in render], 2),
            "render: eyes r": _stat([r["eyes"].r for r in render], 2),
            "render: eyes range": _stat([r["eyes"].range_ratio for r in render], 2),
        }
        for region in ("face", "full"):
            stat = getattr(rows[f"{region}.lpips_vgg"], side)
            column[f"{region} LPIPS-VGG ×1000"] = _mean_std(stat)
        for label, value in column.items():
            cells.setdefault(label, []).append(value)
    lines = [
        "| stage against the target (mean ± std over seeds) | " + " | ".join(columns) + " |",
        "|---|" + "---:|" * len(columns),
    ]
    return lines + [f"| {label} | " + " | ".join(values) + " |" for label, values in cells.items()]


def render_openings(base: str, variants: dict[str, str]) -> Callable[[Path], list[str]]:
    """The render stage's openings of ``bench.expressions`` runs that hold a baseline's cases
    (``<base>_s<seed>``) beside a variant's (``<variant>_s<seed>``): per measure the baseline's
    mean ± std over the seeds, then each variant's with its per-seed gap to the baseline (higher
    is better). ``variants``: ``"<result name>:<the variant's case prefix>"`` -> column label."""
    measures = {
        "mouth r": ("mouth", "r"),
        "mouth range / target's": ("mouth", "range_ratio"),
        "eyes r": ("eyes", "r"),
        "eyes range / target's": ("eyes", "range_ratio"),
    }

    def section(results: Path) -> list[str]:
        docs = {key: load(ExpressionsResult, key.split(":")[0], results).cases for key in variants}

        def values(cases: dict[str, ExpressionCase], prefix: str, part: str, field: str) -> dict[str, float]:
            """seed -> the render stage's ``field`` of ``part`` in the cases ``<prefix>_s<seed>``."""
            return {
                name.removeprefix(f"{prefix}_s"): getattr(case.stages["render"][part], field)
                for name, case in cases.items()
                if name.startswith(f"{prefix}_s")
            }

        lines = [
            "| measure | default | " + " | ".join(variants.values()) + " |",
            "|---|---:|" + "---:|" * len(variants),
        ]
        for label, (part, field) in measures.items():
            first = next(iter(docs.values()))
            baseline = values(first, base, part, field)
            cells = [_stat(list(baseline.values()), 2)]
            for key, cases in docs.items():
                variant = values(cases, key.split(":")[1], part, field)
                seeds = sorted(set(variant) & set(baseline))
                gaps = mean_std([variant[k] - baseline[k] for k in seeds])
                if abs(gaps["mean"]) <= gaps["std"]:
                    word = "no difference"
                else:
                    word = "better" if gaps["mean"] > 0 else "worse"
                change = f"{_signed(gaps['mean'], 2)} ± {gaps['std']:.2f}, {word}"
                cells.append(f"{_stat([variant[k] for k in seeds], 2)} ({change})")
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        return lines

    return section


def real_videos_regions(name: str) -> Callable[[Path], list[str]]:
    """The section of one ``real_videos_compare`` result ``name``, a row per video: each
    region's held-out LPIPS-VGG ×1000 before → after with the paired change, or "no difference"."""

    def section(results: Path) -> list[str]:
        doc = load(RealVideosCompare, name, results)
        lines = ["| video | full | hand | face |", "|---|---|---|---|"]
        for video, regions in doc.comparison.items():
            cells = []
            for region in ("full", "hand", "face"):
                v = regions[region]["lpips_vgg"]
                if v.verdict == "no difference":
                    cells.append(v.verdict)
                else:
                    before, after = v.before.mean * 1e3, v.after.mean * 1e3
                    gap = _percent_gap(v.gap_pct.mean, v.gap_pct.std)
                    cells.append(f"{before:.1f} → {after:.1f} ({gap}, {v.verdict})")
            lines.append(f"| {video.removesuffix('.mp4')} | " + " | ".join(cells) + " |")
        return lines

    return section


def opening_stages(results: Path) -> list[str]:
    """The opening term before and after, stage by stage on the two upper-body clips (gesturing /
    seated; ``expressions/expressions_{before,after}``): the detections and the fit are one per
    clip (their mean over the seeds' cases), the render's mean ± std over the seeds."""
    docs = {
        side: load(ExpressionsResult, f"expressions/expressions_{side}", results).cases
        for side in ("before", "after")
    }
    clips = ("gesturing", "seated")
    measures = (("mouth", "r"), ("mouth", "range_ratio"), ("eyes", "r"), ("eyes", "range_ratio"))

    def cell(side: str, stage: str, part: str, field: str, spread: bool) -> str:
        per_clip = []
        for clip in clips:
            values = [
                getattr(case.stages[stage][part], field)
                for name, case in docs[side].items()
                if name.startswith(f"{clip}_s")
            ]
            per_clip.append(_stat(values, 2) if spread else f"{mean_std(values)['mean']:.2f}")
        return " / ".join(per_clip)

    rows = {
        "detected (what preprocessing stored)": ("after", "detected", False),
        "fitted, before": ("before", "fitted", False),
        "fitted, after": ("after", "fitted", False),
        "render, before": ("before", "render", True),
        "render, after": ("after", "render", True),
    }
    lines = ["| stage | mouth r | mouth range | eyes r | eyes range |", "|---|---|---|---|---|"]
    for label, (side, stage, spread) in rows.items():
        cells = [cell(side, stage, part, field, spread) for part, field in measures]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def attach_variants(
    columns: tuple[tuple[str, str, str, str], ...], rows: tuple[str, ...]
) -> Callable[[Path], list[str]]:
    """Ways of attaching Gaussians to the face, on the two upper-body clips (gesturing / seated):
    per column (label, ``bench.expressions`` result, the folder of the
    ``{gesturing,seated}_before_after`` comparisons that hold its images, and which side of them
    it is: "before" or "after"), the rows among: ``eyes``, ``mouth``, ``face`` (held-out
    LPIPS-VGG), ``face_change`` (paired by seed), ``driving``."""
    clips = {"gesturing": "latentsync_demo3_gesturing.mp4", "seated": "latentsync_demo1_seated.mp4"}

    def section(results: Path) -> list[str]:
        labels = {
            "eyes": ("render eyes r", "render eye range"),
            "mouth": ("render mouth r, range",),
            "face": ("face LPIPS-VGG ×1000",),
            "face_change": ("face, change paired by seed",),
            "driving": ("driving: eyes r, range",),
        }
        table: dict[str, list[str]] = {label: [] for row in rows for label in labels[row]}
        for _, openings, folder, side in columns:
            cases = load(ExpressionsResult, openings, results).cases
            faces = {
                clip: load(RealVideosCompare, f"{folder}/{clip}_before_after", results).comparison[video][
                    "face"
                ]["lpips_vgg"]
                for clip, video in clips.items()
            }

            def render(clip: str, part: str, field: str, cases: dict[str, ExpressionCase] = cases) -> str:
                stages = [c.stages["render"][part] for n, c in cases.items() if n.startswith(f"{clip}_s")]
                return _stat([getattr(stage, field) for stage in stages], 2)

            if "eyes" in rows:
                table["render eyes r"].append(" / ".join(render(c, "eyes", "r") for c in clips))
                table["render eye range"].append(" / ".join(render(c, "eyes", "range_ratio") for c in clips))
            if "mouth" in rows:
                table["render mouth r, range"].append(
                    " / ".join(
                        f"{render(c, 'mouth', 'r')}, {render(c, 'mouth', 'range_ratio')}" for c in clips
                    )
                )
            if "face" in rows:
                table["face LPIPS-VGG ×1000"].append(
                    " / ".join(_mean_std(getattr(faces[c], side)) for c in clips)
                )
            if "face_change" in rows:
                table["face, change paired by seed"].append(
                    "–"
                    if side == "before"
                    else " / ".join(
                        f"{_percent_gap(faces[c].gap_pct.mean, faces[c].gap_pct.std)} ({faces[c].verdict})"
                        for c in clips
                    )
                )
            if "driving" in rows:
                drive = cases["driving"].stages["render"]
                table["driving: eyes r, range"].append(
                    f"{drive['eyes'].r:.2f}, {drive['eyes'].range_ratio:.2f}"
                )
        head = "| gesturing / seated | " + " | ".join(label for label, *_ in columns) + " |"
        return [head, "|---|" + "---|" * len(columns)] + [
            f"| {label} | " + " | ".join(cells) + " |" for label, cells in table.items()
        ]

    return section


REGION_TERMS = {  # clip -> (label, the runs' glob under expressions/region_terms/), baseline first
    "seated": (
        ("baseline, seeds 0-2", "base/real_videos_hands_s?"),
        ("LPIPS-Alex on the face box, weight 0.04", "face04/face04_s0"),
        ("L1 + 0.2 D-SSIM on the face box, weight 0.3", "facew03/facew03_s0"),
        ("the same, weight 1", "facew10/facew10_s0"),
    ),
    "gesturing": (
        ("baseline, seeds 0-2", "base/real_videos_hands_gesturing_s?"),
        ("LPIPS-Alex on the face box, weight 0.04", "face04/face04_gesturing_s2"),
    ),
}


def region_terms(results: Path) -> list[str]:
    """The face's own loss terms, a pilot (``expressions/region_terms/``): each variant's one run
    against the baseline's three seeds; LPIPS ×1000."""
    lines = [
        "| clip | variant | face LPIPS-VGG (held out) | face LPIPS-Alex | face PSNR | full LPIPS-VGG |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for clip, variants in REGION_TERMS.items():
        for label, pattern in variants:
            runs = []
            for _, doc in load_each(RealVideos, f"expressions/region_terms/{pattern}", results):
                (video,) = doc.videos.values()
                runs.append(video.methods["eva"])
            measures = (
                ("face", "lpips_vgg"),
                ("face", "lpips_alex"),
                ("face", "psnr"),
                ("full", "lpips_vgg"),
            )
            cells = []
            for region, metric in measures:
                values = [getattr(run, region)[metric] for run in runs]
                scale, digits = (1e3, 1) if "lpips" in metric else (1.0, 2)
                one = len(values) == 1
                cells.append(f"{scale * values[0]:.{digits}f}" if one else _stat(values, digits, scale))
            lines.append(f"| {clip} | {label} | " + " | ".join(cells) + " |")
    return lines


def per_frame_hands(results: Path) -> list[str]:
    """The clip fit's hands against each frame's hands stage re-run alone (``align.json``;
    docs/alignment.md, the per-frame hand solver)."""
    runs = load(AlignResult, "align", results).synthetic.per_frame_hands
    lines = ["| targets | clip fit | + per-frame hands stage |", "|---|---:|---:|"]
    targets = {"exact_targets": "exact projections and depths", "detections": "MediaPipe detections"}
    for key, label in targets.items():
        r = runs[key]
        lines.append(f"| {label} | {r.clip_fit_mm['hands']:.1f} mm | {r.per_frame_mm['hands']:.1f} mm |")
    return lines


class RegionSensitivityVideo(_Loose):
    regions: dict[str, dict[str, dict[str, float] | int]]
    box_px: dict[str, float]
    methods: dict[str, dict[str, dict[str, float]]]


class RegionSensitivity(_Run):
    """``bench.region_sensitivity``'s result: each region of a test target against itself moved
    or blurred, and the methods' scores of the same crops."""

    videos: dict[str, RegionSensitivityVideo]


def region_sensitivity(results: Path) -> list[str]:
    """taiji's hands and faces scored against themselves shifted or blurred, and eva's avatar
    (``region_sensitivity.json``; docs/alignment.md)."""
    video = load(RegionSensitivity, "region_sensitivity", results).videos["hybrik_taiji.mp4"]
    rows = {f"shifted {k} px": f"shift {k} px" for k in (1, 2, 3, 4)}
    rows["blurred, sigma 1.5 px"] = "blur 1.5 px"
    lines = ["| target against itself | hand | face |", "|---|---:|---:|"]
    for label, key in rows.items():
        hand, face = (1e3 * video.regions[r][key]["lpips_vgg"] for r in ("hand", "face"))
        lines.append(f"| {label} | {hand:.1f} | {face:.1f} |")
    eva = video.methods["eva"]
    lines.append(
        f"| eva's avatar (`real_videos.md`, seed 0) | {1e3 * eva['hand']['lpips_vgg']:.1f} "
        f"| {1e3 * eva['face']['lpips_vgg']:.1f} |"
    )
    return lines


class BlinkSweep(_Run):
    """``bench.blink_sweep``'s result: signed lid gaps (over the eye-corner distance) per blink."""

    blinks: list[float]
    anny: dict[str, list[float]]
    fitted: dict[str, object]
    avatar: dict[str, object]


def blink_sweep(results: Path) -> list[str]:
    """One frame's blink swept from 0 to 1: the signed lid gap on Anny's render and points, the
    fitted face's points and two avatars' renders (``expressions/blink/blink_sweep_{product,eva}``;
    docs/alignment.md, "Where the gesturing clip's blink is lost")."""
    product = load(BlinkSweep, "expressions/blink/blink_sweep_product", results)
    eva = load(BlinkSweep, "expressions/blink/blink_sweep_eva", results)
    frame = product.fitted["frame"]
    rows = {
        "Anny's render, MediaPipe": product.anny["mediapipe"],
        "Anny, the correspondence points": product.anny["model"],
        f"frame {frame}'s fitted face, correspondence points": product.fitted["model"],
        "default avatar (`avatar-product-s0`), MediaPipe on its render": product.avatar["mediapipe"],
        "paper's EVA (`avatar-eva-…_s0`), MediaPipe on its render": eva.avatar["mediapipe"],
    }
    return _sweep_table("blink", product.blinks, rows, closes=True)


def wide_sweep(results: Path) -> list[str]:
    """The gesturing clip's widest-open held-out frame with both eyeWide coefficients swept: the
    fitted face's points and the renders of the `fast` avatar and of the one with the lids'
    six actions' colours (``expressions/lid_colours/wide_sweep_{ce01,lid6}``; docs/alignment.md,
    "The lids' other actions' colours")."""
    fast = load(BlinkSweep, "expressions/lid_colours/wide_sweep_ce01", results)
    lids = load(BlinkSweep, "expressions/lid_colours/wide_sweep_lid6", results)
    frame = fast.fitted["frame"]
    rows = {
        f"frame {frame}'s fitted face, correspondence points": fast.fitted["model"],
        "`fast` (the blinks' colours), MediaPipe on its render": fast.avatar["mediapipe"],
        "the lids' six actions' colours, MediaPipe on its render": lids.avatar["mediapipe"],
    }
    return _sweep_table("eyeWide", fast.blinks, rows, closes=False)


def _sweep_table(action: str, values: list[float], rows: dict[str, list[float]], closes: bool) -> list[str]:
    """One row of signed lid gaps per source over an action's swept ``values``; with ``closes``
    a last column, the value where the gap first reaches zero."""
    head = " | ".join(f"{action} {v:g}" if i == 0 else f"{v:g}" for i, v in enumerate(values))
    last = " gap reaches 0 at |" if closes else ""
    lines = [f"| source | {head} |{last}", "|---|" + "---:|" * (len(values) + closes)]
    for label, gaps in rows.items():
        cells = [_signed(g, 3) for g in gaps]
        if closes:
            at = zero_crossing(values, gaps)
            cells.append("never" if at is None else f"{at:.2f}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def paper_regime(results: Path) -> list[str]:
    """The paper's own regime, with the authors' recipe (``paper_regime.json``)."""
    doc = load(PaperTables, "paper_regime", results)
    rows = {
        "3dgs+body": "3dgs+body",
        "eva": "eva (project)",
        "eva-official-no-cadc": "eva-official-no-cadc (trained on LPIPS-VGG)",
        "eva-official": "eva-official (trained on LPIPS-VGG)",
    }
    return _lpips_table(doc, rows, seeds_column=True)


def service_latency(results: Path) -> list[str]:
    """The render endpoint's latency and throughput (``service.json``)."""
    doc = load(ServiceLatency, "service", results)
    lines = [
        f"`service.md`, {doc.date[:10]}, {doc.machine.split(',')[0]}: a new pose and camera per request "
        "(`pose`) or a new camera only (`camera`, the page's view slider), PNG.",
        "",
        "| changes | image | clients | p50 ms | p95 ms | requests/s |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for r in doc.rows:
        lines.append(
            f"| {r.varies} | {r.size}² | {r.clients} | {r.p50_ms:.0f} | {r.p95_ms:.0f} "
            f"| {r.throughput_rps:.1f} |"
        )
    return lines


class AlignFit(_Loose):
    """One estimate of ``bench.align``'s synthetic section."""

    mpjpe_mm: dict[str, float]
    expression_mm: float
    expression_mm_by_group: dict[str, float]
    head_deg: float


class Agreement(_Loose):
    r: float
    range_ratio: float


class HandsPerFrame(_Loose):
    """``bench.align``'s per-frame hands check: hand MPJPE of the clip fit and of each frame's
    hands stage re-run alone."""

    clip_fit_mm: dict[str, float]
    per_frame_mm: dict[str, float]


class AlignSynthetic(_Loose):
    initial: AlignFit | None = None
    fitted: AlignFit
    openings: dict[str, dict[str, Agreement]]
    per_frame_hands: dict[str, HandsPerFrame] = {}


class AlignResult(_Loose):
    """``bench.align``'s result (the synthetic section)."""

    synthetic: AlignSynthetic


class OneFaceFit(_Loose):
    recovered: dict[str, float]


class OneFace(_Loose):
    """``bench.expression_fit``'s result: one rendered face fitted from the neutral face."""

    fits: dict[str, OneFaceFit]
    detected: dict[str, dict[str, float]]
    projected: dict[str, dict[str, float]]


def opening_term(results: Path) -> list[str]:
    """The opening term before and after: one rendered face (``expressions/one_face``) and
    synthetic ``wild`` (``expressions/correspondence_v2/align`` before, ``openings/align`` after)."""
    one_face = load(OneFace, "expressions/one_face", results)
    face, projected = one_face.fits, one_face.projected
    # A fit that matched MediaPipe's reading of the true render exactly recovers this much of the lids.
    lid_cap = (projected["neutral"]["eyes"] - one_face.detected["truth render"]["eyes"]) / (
        projected["neutral"]["eyes"] - projected["truth"]["eyes"]
    )
    before, after = (
        load(AlignResult, f"expressions/{name}/align", results).synthetic
        for name in ("correspondence_v2", "openings")
    )
    neutral = after.initial
    groups = ("jaw", "lips", "lids", "brows")

    def recovered(fit: OneFaceFit) -> str:
        return f"{100 * fit.recovered['mouth']:.0f}% / {100 * fit.recovered['eyes']:.0f}%"

    def by_group(fit: AlignFit) -> str:
        return " / ".join(f"{fit.expression_mm_by_group[g]:.2f}" for g in groups)

    def openings(doc: AlignSynthetic) -> str:
        o = doc.openings["fitted"]
        return " / ".join(f"{o[part].r:.2f}, {o[part].range_ratio:.2f}" for part in ("mouth", "eyes"))

    def body(fit: AlignFit) -> str:
        return f"{fit.mpjpe_mm['body_in_view']:.1f} / {fit.mpjpe_mm['hands']:.1f}; {fit.head_deg:.1f}"

    rows = [
        (
            "one face, blink 0.8 and jaw 0.5, face → refine: lip / lid change recovered (`one_face.md`)",
            recovered(face["no opening term, from neutral"]),
            f"{recovered(face['from neutral'])} (MediaPipe's own lid gap caps it at {100 * lid_cap:.0f}%)",
        ),
        (
            f"`wild`, expression error, mm (neutral face {neutral.expression_mm:.2f})",
            f"{before.fitted.expression_mm:.2f}",
            f"{after.fitted.expression_mm:.2f}",
        ),
        (
            f"`wild`, per group: jaw / lips / lids / brows, mm (neutral {by_group(neutral)})",
            by_group(before.fitted),
            by_group(after.fitted),
        ),
        (
            "`wild`, fitted opening against the truth: mouth r, range / eyes r, range",
            openings(before),
            openings(after),
        ),
        (
            "`wild`, body in view / hands MPJPE, mm; head rotation, degrees",
            body(before.fitted),
            body(after.fitted),
        ),
    ]
    return ["| measure | before | after |", "|---|---:|---|"] + [f"| {a} | {b} | {c} |" for a, b, c in rows]


class FitLeverRun(_Loose):
    case: str
    seed: int
    variant: str
    fit_iou: float
    joint_error_px: dict[str, float]
    skin_error_px: dict[str, float]


class FitLevers(_Run):
    """``bench.fit_levers``' report: the fit against the truth on the hard clips."""

    runs: list[FitLeverRun]


class CloseupLever(_Loose):
    variant: str
    seed: int
    round: int = 1  # the first round's runs recorded none
    truth: dict[str, float]


class CloseupLevers(_Loose):
    """``bench.closeup_levers``' result: one run per variant, seed and round."""

    runs: list[CloseupLever]


class ExactFit(_Loose):
    mpjpe_mm: dict[str, float]


class AlignExact(AlignSynthetic):
    fitted_to_exact_targets: ExactFit


class AlignExactResult(_Loose):
    synthetic: AlignExact


def body_prior(results: Path) -> list[str]:
    """The articulation prior on Anny's redundant bones, without and with (``body_prior/``): the
    hard clips' fit (seed 0), the close-up's avatar (``closeup_levers.json``, round 3) and the
    synthetic ``wild`` fit."""
    fits = load(FitLevers, "body_prior/fit_levers_body_prior", results).runs
    avatars = [r for r in load(CloseupLevers, "closeup_levers", results).runs if r.round == 3]
    wild = {
        side: load(AlignExactResult, f"body_prior/{name}", results).synthetic
        for side, name in (("baseline", "align_before"), ("body_prior", "align_subject_axes"))
    }

    def fit(case: str, variant: str) -> str:
        (r,) = [r for r in fits if r.case == case and r.variant == variant and r.seed == 0]
        skin, joints = r.skin_error_px, r.joint_error_px
        return (
            f"{r.fit_iou:.3f} / {skin['torso']:.1f} / {skin['torso slide']:.1f} / {joints['shoulders']:.1f}"
        )

    def avatar(variant: str) -> str:
        runs = sorted((r for r in avatars if r.variant == variant), key=lambda r: r.seed)
        return " / ".join(f"{1000 * r.truth['lpips_vgg']:.1f}" for r in runs)

    def on_detections(variant: str) -> str:
        f = wild[variant].fitted
        mm = " / ".join(f"{f.mpjpe_mm[k]:.1f}" for k in ("body_in_view", "body", "hands"))
        return f"{mm}; {f.expression_mm:.2f}; {f.head_deg:.1f}"

    detections = "`wild`, on detections: body in view / all / hands MPJPE, mm; expression, mm; head, degrees"
    rows = {
        "close-up fit, seed 0: silhouette IoU / torso skin px / torso slide px / shoulders px": lambda v: fit(
            "closeup", v
        ),
        "clean clip fit, seed 0: the same": lambda v: fit("clean", v),
        "close-up avatar, truth LPIPS-VGG ×1000, seeds 0 / 1 / 2 (`closeup_levers.md`, round 3)": avatar,
        detections: on_detections,
        "`wild`, fitted to exact targets: body in view MPJPE, mm": lambda v: (
            f"{wild[v].fitted_to_exact_targets.mpjpe_mm['body_in_view']:.1f}"
        ),
    }
    lines = ["| measure | without | with |", "|---|---:|---:|"]
    return lines + [
        f"| {label} | {cell('baseline')} | {cell('body_prior')} |" for label, cell in rows.items()
    ]


def calibration_wild(results: Path) -> list[str]:
    """The face mesh's calibration on synthetic ``wild``: the fit before, with the calibration at
    the face stage's old and new iterations, and this tree (``expressions/calibration/``)."""
    rows = {
        "align_before": "before (face stage 40, no calibration)",
        "align_calibration_face40": "calibration, face stage 40 (`align_calibration_face40.md`)",
        "align_all_landmarks": "calibration of every landmark, 200 (`align_all_landmarks.md`)",
        "align": "**this tree**: eye outlines uncalibrated, 200",
    }
    lines = [
        "| fit | expression, mm | jaw / lips / lids / brows, mm | fitted mouth: r, range "
        "| fitted eyes: r, range | body in view / hands, mm; head, ° |",
        "|---|---:|---|---|---|---|",
    ]
    for name, label in rows.items():
        doc = load(AlignResult, f"expressions/calibration/{name}", results).synthetic
        fit, o = doc.fitted, doc.openings["fitted"]
        groups = " / ".join(f"{fit.expression_mm_by_group[g]:.2f}" for g in ("jaw", "lips", "lids", "brows"))
        mouth, eyes = o["mouth"], o["eyes"]
        lines.append(
            f"| {label} | {fit.expression_mm:.2f} | {groups} | {mouth.r:.2f}, {mouth.range_ratio:.2f} "
            f"| {eyes.r:.2f}, {eyes.range_ratio:.2f} | {fit.mpjpe_mm['body_in_view']:.1f} / "
            f"{fit.mpjpe_mm['hands']:.1f}; {fit.head_deg:.1f} |"
        )
    return lines


class CalibrationDraw(_Loose):
    """One calibration of ``expressions/calibration/draws/wild_fits.json`` and wild's fit with it."""

    eye_px: int
    samples: int
    seed: int
    shipped: bool
    expression_mm: float
    groups_mm: dict[str, float]


class CalibrationDraws(_Loose):
    runs: list[CalibrationDraw]


def calibration_draws(results: Path) -> list[str]:
    """Synthetic ``wild``'s expression error over calibrations built from several random draws of
    expressions, per size of the rendered face (``expressions/calibration/draws/``)."""
    runs = load(CalibrationDraws, "expressions/calibration/draws/wild_fits", results).runs
    groups = ("jaw", "lips", "lids", "brows")
    lines = [
        "| renders' eye corners, px (expressions per draw) | draws | expression, mm: each draw "
        "| mean ± std | jaw / lips / lids / brows, mm (mean) |",
        "|---|---:|---|---:|---|",
    ]
    for px, samples in sorted({(r.eye_px, r.samples) for r in runs}, key=lambda k: (-k[0], k[1])):
        got = sorted((r for r in runs if (r.eye_px, r.samples) == (px, samples)), key=lambda r: r.seed)
        each = ", ".join(f"{r.expression_mm:.2f}" + (" (shipped)" if r.shipped else "") for r in got)
        mm = [r.expression_mm for r in got]
        spread = f"{statistics.mean(mm):.2f} ± {statistics.stdev(mm):.2f}" if len(mm) > 1 else f"{mm[0]:.2f}"
        by_group = " / ".join(f"{statistics.mean(r.groups_mm[g] for r in got):.2f}" for g in groups)
        lines.append(f"| {px} ({samples}) | {len(got)} | {each} | {spread} | {by_group} |")
    return lines


class BoundedFit(_Loose):
    """One full fit of ``expressions/bounded/fits.py``: a clip's openings against its stored
    detections, or ``wild``'s errors against the truth."""

    variant: str
    clip: str
    seconds: float
    eyes: Agreement | None = None
    mouth: Agreement | None = None
    expression_mm: float | None = None
    groups_mm: dict[str, float] | None = None
    mpjpe_mm: dict[str, float] | None = None


class BoundedFits(_Run):
    runs: list[BoundedFit]


def expression_range_fits(results: Path) -> list[str]:
    """The fit with the expression kept in its range against the penalty's fit: per upper-body clip
    the fitted openings against the detections, both fitted in full by one tree
    (``expressions/bounded/fits``), and ``bench.align``'s synthetic ``wild`` before
    (``expressions/bounded/align_before``) and now (``align``)."""
    runs = {(r.variant, r.clip): r for r in load(BoundedFits, "expressions/bounded/fits", results).runs}
    lines = ["| measure | penalty (before) | in range (L-BFGS-B) |", "|---|---:|---:|"]
    for clip in ("gesturing", "seated"):
        for part in ("eyes", "mouth"):
            got = [getattr(runs[v, clip], part) for v in ("penalty", "bounded")]
            lines.append(f"| {clip}: fitted {part} r | " + " | ".join(f"{g.r:.2f}" for g in got) + " |")
            lines.append(
                f"| {clip}: fitted {part} range over the detections' | "
                + " | ".join(f"{g.range_ratio:.2f}" for g in got)
                + " |"
            )
    fits = [load(AlignRun, name, results).synthetic for name in ("expressions/bounded/align_before", "align")]
    neutral = fits[0].initial.expression_mm
    rows = {
        f"`wild`, expression, mm (neutral face {neutral:.2f})": lambda s: f"{s.fitted.expression_mm:.2f}",
        "`wild`, jaw / lips / lids / brows, mm": lambda s: " / ".join(
            f"{s.fitted.expression_mm_by_group[g]:.2f}" for g in ("jaw", "lips", "lids", "brows")
        ),
        "`wild`, body in view / hands MPJPE, mm": lambda s: (
            f"{s.fitted.mpjpe_mm['body_in_view']:.1f} / {s.fitted.mpjpe_mm['hands']:.1f}"
        ),
        "`wild`, head rotation, degrees": lambda s: f"{s.fitted.head_deg:.1f}",
        f"`wild`, seconds to fit {fits[0].frames} frames (two threads)": lambda s: (
            f"{s.seconds.fit_total:.1f}"
        ),
    }
    for label, cell in rows.items():
        lines.append(f"| {label} | " + " | ".join(cell(s) for s in fits) + " |")
    return lines


STAGE_LINE = re.compile(
    r"(?P<optimiser>\S+) (?P<stage>\w+): (?P<calls>\d+) loss evaluations "
    r"\(of (?P<iterations>\d+) iterations\), loss (?P<first>\S+) -> (?P<last>\S+), "
    r"(?P<outside>\d+)% of the coefficients outside \[0, 1\], lowest (?P<lowest>\S+), (?P<seconds>\d+) s"
)


def expression_range_stages(results: Path) -> list[str]:
    """The face and refine stages from a clip's stored fit, by each optimiser
    (``expressions/bounded/stages.log``, one line per optimiser and stage)."""
    text = (results / "expressions/bounded/stages.log").read_text()
    found = [STAGE_LINE.fullmatch(line.strip()) for line in text.splitlines() if line.strip()]
    if not found or not all(found):
        raise ValueError("expressions/bounded/stages.log: a line that is not a stage's")
    lines = [
        "| optimiser | stage | loss evaluations (iterations) | loss, first → last "
        "| coefficients outside [0, 1] | lowest coefficient |",
        "|---|---|---:|---|---:|---:|",
    ]
    for m in found:
        optimiser = "torch L-BFGS, range penalty" if m["optimiser"] == "penalty" else "L-BFGS-B"
        lines.append(
            f"| {optimiser} | {m['stage']} | {m['calls']} ({m['iterations']}) | {m['first']} → {m['last']} "
            f"| {m['outside']}% | {m['lowest']} |"
        )
    return lines


def _bounded_fit_seconds(results: Path) -> str:
    """``bench.align``'s time to fit ``wild``, before L-BFGS-B and now: "A s → B s"."""
    before = load(AlignRun, "expressions/bounded/align_before", results).synthetic.seconds.fit_total
    after = load(AlignRun, "align", results).synthetic.seconds.fit_total
    return f"{before:.1f} s → {after:.1f} s"


class AlignEstimate(AlignFit):
    """An estimate of ``bench.align``'s synthetic section with its image-space errors."""

    px_vs_ground_truth: dict[str, float]
    face_mesh_px_per_frame: dict[str, float]


class AlignSeconds(_Loose):
    fit_total: float


class AlignMeasured(_Loose):
    """``bench.align``'s synthetic section, the fields ``align_measurements`` reads."""

    frames: int
    image_size: list[int]
    detection_px_vs_ground_truth: dict[str, float]
    initial: AlignEstimate
    fitted: AlignEstimate
    ground_truth_params: AlignEstimate
    seconds: AlignSeconds


class AlignRun(_Run):
    machine: str
    synthetic: AlignMeasured


def align_measurements(results: Path) -> list[str]:
    """``docs/alignment.md``, "Measurements": the fit on synthetic ``wild`` (``align.json``)."""
    doc = load(AlignRun, "align", results)
    s = doc.synthetic
    first, fit, truth = s.initial, s.fitted, s.ground_truth_params
    groups = ", ".join(f"{g} {fit.expression_mm_by_group[g]:.2f}" for g in ("jaw", "lips", "lids", "brows"))
    threads = doc.machine.split(" with ")[1].split(",")[0] if " with " in doc.machine else "?"
    return [
        f"`python -m bench align` → `bench/results/align.md` (synthetic `wild`, {s.frames} frames at "
        f"{s.image_size[0]} px, MediaPipe on the renders, ground truth known; {_when(doc)}, {threads}):",
        f"- fitted hand MPJPE {fit.mpjpe_mm['hands']:.1f} mm "
        f"(initial estimate {first.mpjpe_mm['hands']:.1f});",
        f"- body MPJPE {fit.mpjpe_mm['body_in_view']:.1f} mm over the joints in view "
        f"({fit.mpjpe_mm['body']:.1f} mm over all joints: the legs of a waist-up frame are guesses);",
        f"- hand 2D error {fit.px_vs_ground_truth['hands']:.2f} px (detector "
        f"{s.detection_px_vs_ground_truth['hands']:.1f} px);",
        f"- face-mesh re-projection {fit.face_mesh_px_per_frame['median']:.2f} px per frame (median; "
        f"{truth.face_mesh_px_per_frame['median']:.2f} px for the true parameters, the correspondence's own "
        "error);",
        f"- expression error {fit.expression_mm:.2f} mm against {first.expression_mm:.2f} mm for the initial "
        f"neutral face ({groups} mm);",
        f"- head rotation error {fit.head_deg:.1f} degrees (initial {first.head_deg:.1f});",
        f"- fitting {s.frames} frames took {s.seconds.fit_total:.1f} s (goal 60 s).",
    ]


class CurvePoint(_Loose):
    step: int
    seeds: int
    train_seconds: Stat
    full: Stat
    hand: Stat
    face: Stat


class TimeToQuality(_Run):
    """``bench.time_to_quality``'s merged result."""

    note: str | None = None
    curves: dict[str, list[CurvePoint]]


def time_to_quality(results: Path) -> list[str]:
    """Each method's held-out LPIPS-VGG at each checkpoint against its training seconds
    (``time_to_quality.json``; ``docs/baselines.md``, ``docs/eva-contributions.md``)."""
    doc = load(TimeToQuality, "time_to_quality", results)
    lines = [
        f"`time_to_quality.md`, {_when(doc)}" + (f" ({doc.note})" if doc.note else "") + ": LPIPS-VGG "
        "×1000 on every 4th novel-pose frame, mean ± std over the seeds; training seconds without "
        "the evaluation.",
        "",
        "| method | iteration | train (s) | full | hand | face |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for method, points in doc.curves.items():
        for p in points:
            lines.append(
                f"| {method} | {p.step} | {p.train_seconds.mean:.0f} ± {p.train_seconds.std:.0f} "
                f"| {_mean_std(p.full)} | {_mean_std(p.hand)} | {_mean_std(p.face)} |"
            )
    return lines


class RegionScores(_Loose):
    lpips_vgg: float


class EvalResult(_Loose):
    """``eva eval --json``: the fields a table reads."""

    num_gaussians: int
    train_seconds: float | None
    regions: dict[str, RegionScores]


class StageAgreement(_Loose):
    r: float
    range_ratio: float


class CloseupImages(_Loose):
    lpips_vgg: float


class ExpressionCase(_Loose):
    """One case of ``bench.expressions``' result."""

    stages: dict[str, dict[str, StageAgreement | int]]
    closeup_images: CloseupImages | None = None


class ExpressionsResult(_Loose):
    cases: dict[str, ExpressionCase]


def _stat(values: list[float], digits: int, scale: float = 1.0) -> str:
    return fmt(mean_std(values), scale, digits)


# Issue 39's face goal: each variant's ``eva eval`` against the avatars of the main the issue was
# filed on (``expressions/calibration/eval/eval-<clip>-base-s*.json``), paired by seed.
FACE_GOAL_VARIANTS = (
    ("def", "`fast`, this tree"),
    ("dp", "default preset"),
    ("dpc", "default preset, close-ups"),
)


def face_goal(results: Path) -> list[str]:
    """The face and full-image LPIPS-VGG of the filing's avatars and of this tree's at ``fast``,
    at the default preset and at the default preset with the face close-ups, each paired by seed
    against the filing's (``expressions/closeup_preset/eval_<clip>_base_<variant>.json``)."""
    head = " | ".join(label for _, label in FACE_GOAL_VARIANTS)
    lines = [
        f"| LPIPS-VGG ×1000, mean ± std, 3 seeds (gap to the filing's, per seed) "
        f"| the filing's main, `fast` | {head} |",
        "|---|---:|" + "---:|" * len(FACE_GOAL_VARIANTS),
    ]
    for clip in ("gesturing", "seated"):
        for region in ("face", "full"):
            cells, base = [], None
            for tag, _ in FACE_GOAL_VARIANTS:
                doc = load(EvalPaired, f"expressions/closeup_preset/eval_{clip}_base_{tag}", results)
                row = next(r for r in doc.rows if (r.region, r.metric) == (region, "lpips_vgg"))
                base = base or row.before
                gap = _percent_gap(row.gap_percent.mean, row.gap_percent.std)
                cells.append(f"{_mean_std(row.after)} ({gap}, {row.verdict})")
            lines.append(f"| {clip}, {region} | {_mean_std(base)} | {' | '.join(cells)} |")
    return lines


def closeup_densify(results: Path) -> list[str]:
    """The face close-ups with and without densifying from them, against the frames alone, on
    the two upper-body clips (``expressions/closeup_densify/``, its README)."""
    here, base = "expressions/closeup_densify", "expressions/calibration"
    variants = {"noeyes": "frames only (the default)", "f": "close-ups", "fd": "close-ups, densified"}
    clips, seeds = ("gesturing", "seated"), (0, 1, 2)

    evals = {  # (clip, variant) -> its seeds' eval results, each file read once
        (c, v): [
            load(EvalResult, f"{base if v == 'noeyes' else here}/eval/eval-{c}-{v}-s{s}", results)
            for s in seeds
        ]
        for c in clips
        for v in variants
    }

    closeup = load(ExpressionsResult, f"{here}/expressions_closeups_closeup", results).cases
    frames = {
        **load(ExpressionsResult, f"{base}/expressions_noeyes", results).cases,
        **load(ExpressionsResult, f"{here}/expressions_closeups_frames", results).cases,
    }

    def row(label: str, cell: Callable[[str, str], str]) -> str:
        return f"| {label} | " + " | ".join(" / ".join(cell(c, v) for c in clips) for v in variants) + " |"

    def openings(measure: str) -> Callable[[str, str], str]:
        def cell(clip: str, v: str) -> str:
            render = [frames[f"{clip}_{v}_s{s}"].stages["render"][measure] for s in seeds]
            r = sum(a.r for a in render) / len(render)
            ratio = sum(a.range_ratio for a in render) / len(render)
            return f"{r:.2f}, {ratio:.2f}"

        return cell

    def region(name: str) -> Callable[[str, str], str]:
        return lambda c, v: _stat([e.regions[name].lpips_vgg for e in evals[c, v]], 1, 1e3)

    def closeup_lpips(c: str, v: str) -> str:
        return _stat([closeup[f"{c}_{v}_s{s}"].closeup_images.lpips_vgg for s in seeds], 1, 1e3)

    def gaussians(c: str, v: str) -> str:
        return f"{sum(e.num_gaussians for e in evals[c, v]) / len(seeds):,.0f}"

    def seconds(c: str, v: str) -> str:
        return f"{sum(e.train_seconds for e in evals[c, v]) / len(seeds):.1f}"

    return [
        "| mean ± std, 3 seeds (gesturing / seated) | " + " | ".join(variants.values()) + " |",
        "|---|---|---|---|",
        row("Gaussians", gaussians),
        row("training, s (two runs sharing the cores; the default's trained that morning)", seconds),
        row("close-up LPIPS-VGG ×1000", closeup_lpips),
        row("face LPIPS-VGG ×1000, 512 px", region("face")),
        row("full LPIPS-VGG ×1000", region("full")),
        row("render at 512 px: eyes r, range over the target's", openings("eyes")),
        row("render at 512 px: mouth r, range", openings("mouth")),
    ]


class TrainRun(_Run):
    """One labelled section of ``train.json`` (``bench.train``; older sections hold strings)."""

    train_seconds: float
    num_gaussians: int


class RealVideoMethod(_Loose):
    train_seconds: float
    n_gaussians: int
    full: dict[str, float | None] = {}
    hand: dict[str, float | None] = {}
    face: dict[str, float | None] = {}


class RealVideo(_Loose):
    methods: dict[str, RealVideoMethod]


class RealVideos(_Run):
    """``bench.real_videos``' result (the training times)."""

    videos: dict[str, RealVideo]


REAL_VIDEOS_HISTORY = {  # column label -> the eva runs' result files (several: mean ± std over them)
    "before this work": ("real_videos_before",),
    "detection ≤ 1280 px (`real_videos.md` at 93627af)": ("real_videos_history/real_videos_93627af",),
    "+ wide body stage, hands turned again (`real_videos.md` at c3261c7)": (
        "real_videos_history/real_videos_c3261c7",
    ),
    "+ outline, face depths and fallback (seed 0)": ("real_videos_bs_seed0",),
    "the same, 3 seeds (`real_videos_bs_seed{0,1,2}`)": tuple(f"real_videos_bs_seed{s}" for s in range(3)),
    "+ SSIM weight 0.2 (now, 3 seeds, `real_videos_ssim_seed{0,1,2}`)": tuple(
        f"real_videos_ssim_seed{s}" for s in range(3)
    ),
}


def real_videos_history(results: Path) -> list[str]:
    """eva on the two full-body reference videos through the alignment work, LPIPS-VGG ×1000
    full / hand / face per step (docs/alignment.md; ``real_videos_history/`` holds the two
    intermediate results from git history)."""
    columns = {
        label: [load(RealVideos, name, results).videos for name in names]
        for label, names in REAL_VIDEOS_HISTORY.items()
    }
    videos = list(next(iter(columns.values()))[0])
    lines = ["| video | " + " | ".join(columns) + " |", "|---|" + "---|" * len(columns)]
    for video in videos:
        cells = []
        for runs in columns.values():
            methods = [run[video].methods["eva"] for run in runs]
            cells.append(" / ".join(region_lpips(methods)))
        lines.append(f"| {video.removesuffix('.mp4')} | " + " | ".join(cells) + " |")
    return lines


class TestSuite(_Run):
    """``bench.test_suite``'s result."""

    exit_code: int
    wall_seconds: float
    pytest_seconds: float | None
    counts: dict[str, int]
    fresh_clone: bool = False


class FirstContact(_Run):
    """``bench.first_contact``'s result."""

    exit_code: int
    total_seconds: float
    steps_seconds: dict[str, float]


class Rasterizer(_Run):
    """``bench.rasterizer``'s result (its own verdicts on its targets)."""

    targets: list[str]


SPEED_TRAIN_RUNS = {
    "default": "controlled-bench-seed0/default@setup_2000",
    "eva": "controlled-bench-seed0/default/eva@setup_2000",
}
"""The ``train.json`` sections the targets table quotes: the latest 2,000-iteration runs of each."""
SPEED_REAL_VIDEO = ("speed_fast/real_videos_fast_mmpose", "mmpose_body3d_demo.mp4")


NOVEL_POSE_SPLITS = ("near", "far", "view", "far_view")
NOVEL_POSE_CANDIDATES = {
    "before": "before",
    "thin": "**thin** (kept)",
    "scale_cap": "scale_cap",
    "thin_cap": "thin_cap (both)",
    "final_prune": "final_prune",
    "pose_noise": "pose_noise",
    "random_bg": "random_bg",
    "sh0": "sh0",
    "skinning_prior": "skinning_prior",
    "knn_std": "knn_std",
}
"""docs/novel-views.md's rows of ``novel_pose.json`` (row -> its label there), in its order."""


def _percent(stat: Stat) -> str:
    return f"{stat.mean * 100:.2f} ± {stat.std * 100:.2f}"


class NovelPoseFrame(_Loose):
    pose_deg: float
    yaw_deg: float


class NovelPoseFrames(_Loose):
    per_frame: dict[str, NovelPoseFrame]


class NovelPoseFramesRun(_Loose):
    splits: dict[str, NovelPoseFrames]


class NovelPoseFramesRow(_Loose):
    runs: list[NovelPoseFramesRun]


class NovelPoseNovelty(_Loose):
    methods: dict[str, NovelPoseFramesRow]


NOVEL_POSE_SPLIT_WHAT = {
    "near": "other takes of the training generator",
    "far": "a take raising the arms above the shoulders",
    "view": "training poses from 35° and 70°",
    "far_view": "far poses from 35°",
}


def novel_pose_splits(results: Path) -> list[str]:
    """How new each test split of ``novel_pose.json`` is: the largest joint angle to the nearest
    training pose and the camera's yaw about the body, over the first row's runs' frames."""
    runs = next(iter(load(NovelPoseNovelty, "novel_pose", results).methods.values())).runs
    lines = [
        "| split | what it is | largest joint angle to the nearest training pose, median [min, max] "
        "| camera yaw about the body |",
        "|---|---|---|---|",
    ]
    for split, what in NOVEL_POSE_SPLIT_WHAT.items():
        frames = [f for run in runs for f in run.splits[split].per_frame.values()]
        pose = sorted(f.pose_deg for f in frames)
        yaw = [f.yaw_deg for f in frames]
        angles = f"{statistics.median(pose):.0f}° [{pose[0]:.0f}, {pose[-1]:.0f}]"
        yaws = f"{_signed(min(yaw), 0).lstrip('+')}° to {_signed(max(yaw), 0).lstrip('+')}°"
        lines.append(f"| {split} | {what} | {angles} | {yaws} |")
    return lines


def novel_pose_candidates(results: Path) -> list[str]:
    """Each candidate of the novel-pose work: full-image LPIPS-VGG ×1000 per split, debris % from
    the new views (docs/novel-views.md, "What was tried")."""
    doc = load(NovelPose, "novel_pose", results)
    lines = [
        "| row | seeds | " + " | ".join(NOVEL_POSE_SPLITS) + " | debris, view | debris, far_view |",
        "|---|---|" + "---:|" * (len(NOVEL_POSE_SPLITS) + 2),
    ]
    for name, label in NOVEL_POSE_CANDIDATES.items():
        row = doc.methods[name]
        cells = [_mean_std(row.splits[s].full["lpips_vgg"]) for s in NOVEL_POSE_SPLITS]
        cells += [_percent(row.splits[s].debris) for s in ("view", "far_view")]
        lines.append(f"| {label} | {len(row.seeds)} | " + " | ".join(cells) + " |")
    return lines


def novel_pose_before_after(results: Path) -> list[str]:
    """``before`` against ``thin`` per split: LPIPS-VGG ×1000 per region, debris and holes %
    (docs/novel-views.md, "The product now")."""
    doc = load(NovelPose, "novel_pose", results)
    lines = [
        "| split | row | full | hand | face | arm | debris % | holes % |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for split in NOVEL_POSE_SPLITS:
        for name in ("before", "thin"):
            s = doc.methods[name].splits[split]
            cells = [_mean_std(getattr(s, region)["lpips_vgg"]) for region in ("full", "hand", "face", "arm")]
            cells += [_percent(s.debris), _percent(s.holes)]
            lines.append(f"| {split} | {name} | " + " | ".join(cells) + " |")
    return lines


def _signed(value: float, digits: int = 1) -> str:
    return f"{value:+.{digits}f}".replace("-", "\u2212")


def _percent_gap(mean: float, std: float) -> str:
    """A paired relative gap as the docs write it: "−5.4 ± 0.5%"."""
    return f"{_signed(mean)} ± {std:.1f}%"


def novel_pose_goals(results: Path) -> list[str]:
    """``thin`` against ``before``, paired by seed, against the novel-pose issue's goals
    (docs/novel-views.md, "The product now")."""
    thin = load(NovelPose, "novel_pose", results).methods["thin"]
    gaps = novel_pose_gaps(results)

    def lpips_goal(label: str, split: str, region: str, met: Callable[[float], bool]) -> str:
        verdict, g = gaps[split, region]
        result = f"{_percent_gap(g['mean'], g['std'])} ({verdict})"
        return f"| {label} | {result} | {'yes' if met(g['mean']) else 'no'} |"

    debris = {split: thin.splits[split].debris.mean * 100 for split in ("near", "view", "far_view")}
    debris_met = max(debris["view"], debris["far_view"]) <= 2 * debris["near"]
    return [
        "| goal | result | met |",
        "|---|---|---|",
        lpips_goal("far full LPIPS-VGG −15%", "far", "full", lambda m: m <= -15),
        lpips_goal("near no worse than +2%", "near", "full", lambda m: m <= 2),
        lpips_goal("view full LPIPS-VGG −25%", "view", "full", lambda m: m <= -25),
        lpips_goal("view face LPIPS-VGG −30%", "view", "face", lambda m: m <= -30),
        f"| debris on view and far_view at most 2× the training view's | view {debris['view']:.2f}%, "
        f"far_view {debris['far_view']:.2f}%, against {debris['near']:.2f}% in near poses from the "
        f"training camera | {'yes' if debris_met else 'no'} |",
        "| the paper tables unchanged | the paper's methods do not use the term (below) | yes |",
    ]


def novel_pose_gaps(
    results: Path,
    metric: str = "lpips_vgg",
    result: str = "novel_pose",
    row: str = "thin",
    baseline: str = "before",
) -> dict[tuple[str, str], tuple[str, dict]]:
    """``row`` against ``baseline`` in ``<result>.json`` (``bench novel_pose``), paired by seed:
    {(split, region): ``stats.compare_paired``'s (verdict, mean_std of the per-seed relative gaps
    in %)}; regions ``debris`` and ``holes`` for the debris and the holes."""
    doc = load(NovelPose, result, results)
    by_seed = {name: {r.seed: r for r in doc.methods[name].runs} for name in (baseline, row)}
    seeds = sorted(by_seed[baseline])
    if seeds != sorted(by_seed[row]):
        raise ValueError(f"{result}.json: {baseline} and {row} ran on different seeds")
    out = {}
    runs = [r for by in by_seed.values() for r in by.values()]
    closeups = all(s.closeup is not None for r in runs for s in r.splits.values())
    for split in NOVEL_POSE_SPLITS:
        for region in ("full", "hand", "face", "arm", "debris", "holes", *(("closeup",) if closeups else ())):

            def value(run: NovelPoseRun, split: str = split, region: str = region) -> float:
                s = run.splits[split]
                return getattr(s, region) if region in ("debris", "holes") else getattr(s, region)[metric]

            values = {name: [value(runs[k]) for k in seeds] for name, runs in by_seed.items()}
            lower = region in ("debris", "holes") or "lpips" in metric
            out[split, region] = compare_paired(values[row], values[baseline], lower_is_better=lower)
    return out


def novel_pose_rows(
    rows: dict[str, str], regions: dict[str, str], result: str, baseline: str
) -> Callable[[Path], list[str]]:
    """A section: each of ``rows`` of ``<result>.json`` (``bench novel_pose``) against
    ``baseline``, per split and region (LPIPS-VGG ×1000; ``holes`` in %), mean ± std over the
    seeds, and the gap paired by seed with its verdict."""

    def section(results: Path) -> list[str]:
        doc = load(NovelPose, result, results)
        gaps = {row: novel_pose_gaps(results, result=result, row=row, baseline=baseline) for row in rows}
        seeds = _seeds(doc.methods[baseline].seeds)
        lines = [
            f"| LPIPS-VGG ×1000, seeds {seeds} (gap: per seed) | the default | "
            + " | ".join(rows.values())
            + " |",
            "|---|---:|" + "---:|" * len(rows),
        ]
        for split in NOVEL_POSE_SPLITS:
            for region, label in regions.items():

                def stat(m, split: str = split, region: str = region) -> Stat:
                    s = m.splits[split]
                    return (
                        _scaled(s.holes, 1e2)
                        if region == "holes"
                        else _scaled(getattr(s, region)["lpips_vgg"], 1e3)
                    )

                digits = 2 if region == "holes" else 1
                cells = [_mean_std(stat(doc.methods[baseline]), 1.0, digits)]
                for row in rows:
                    verdict, g = gaps[row][split, region]
                    gap = _percent_gap(g["mean"], g["std"])
                    cells.append(f"{_mean_std(stat(doc.methods[row]), 1.0, digits)} ({gap}, {verdict})")
                lines.append(f"| {split}: {label} | " + " | ".join(cells) + " |")
        return lines

    return section


# The face close-ups and the 2D filter on the synthetic novel-pose benchmark
# (``novel_pose_closeups/``): rows against the default, and the regions they bear on.
novel_pose_closeups = novel_pose_rows(
    {
        "face_closeups": "close-ups",
        "antialiased": "antialiased",
        "face_closeups_antialiased": "close-ups, antialiased",
        "face_closeups_antialiased_eps01": "close-ups, antialiased, 0.1 px² filter",
        "face_closeups_eps01": "close-ups, classic, 0.1 px²",
    },
    {"closeup": "head at 256 px", "face": "face in the frame", "full": "full frame"},
    result="novel_pose_closeups/novel_pose_closeups",
    baseline="thin_blink_colours",
)
# The ridge on the expression colours' offsets (``expressions/lid_colours/``).
novel_pose_lid_ridge = novel_pose_rows(
    {"blink_colours_ridge": "blinks, ridge 1e-3", "lid_colours_ridge": "six lid actions, ridge 1e-3"},
    {"face": "face in the frame", "closeup": "head at 256 px", "full": "full frame"},
    result="expressions/lid_colours/novel_pose_lid_ridge",
    baseline="classic_eps01",
)
novel_pose_filters = novel_pose_rows(
    {
        "antialiased": "antialiased, 0.3 px²",
        "antialiased_eps01": "antialiased, 0.1 px²",
        "classic_eps01": "classic, 0.1 px²",
    },
    {"full": "full frame", "face": "face", "hand": "hand", "closeup": "head at 256 px", "holes": "holes, %"},
    result="novel_pose_closeups/novel_pose_closeups",
    baseline="thin_blink_colours",
)


def novel_pose_gap(results: Path, name: str) -> str:
    """The figure ``novel_pose_gap/<result>/<row>/<baseline>/<split>.<region>[.<metric>]``: a
    ``bench novel_pose`` row's paired gap against another's with its verdict (LPIPS-VGG unless
    ``metric``), e.g. ``novel_pose_gap/expressions/events/novel_pose_events/blink_events/
    thin_blink_colours/view.full`` -> "+1.7 ± 0.7%, worse"."""
    result, row, baseline, key = name.rsplit("/", 3)
    split, region, *metric = key.split(".")
    verdict, g = novel_pose_gaps(results, *metric, result=result, row=row, baseline=baseline)[split, region]
    return f"{_percent_gap(g['mean'], g['std'])}, {verdict}"


def _novel_pose_gap(split: str, region: str) -> Callable[[Path], str]:
    def figure(results: Path) -> str:
        g = novel_pose_gaps(results)[split, region][1]
        return _percent_gap(g["mean"], g["std"])

    return figure


def _novel_pose_cut(split: str, region: str) -> Callable[[Path], str]:
    def figure(results: Path) -> str:
        return f"{-novel_pose_gaps(results)[split, region][1]['mean']:.0f}%"

    return figure


def _novel_pose_cut_range(region: str) -> Callable[[Path], str]:
    def figure(results: Path) -> str:
        gaps = novel_pose_gaps(results)
        cuts = sorted(-gaps[split, region][1]["mean"] for split in NOVEL_POSE_SPLITS)
        return f"{cuts[0]:.0f}-{cuts[-1]:.0f}%"

    return figure


def _novel_pose_holes(split: str) -> Callable[[Path], str]:
    def figure(results: Path) -> str:
        doc = load(NovelPose, "novel_pose", results)
        before, thin = (doc.methods[name].splits[split].holes.mean * 100 for name in ("before", "thin"))
        return f"{before:.2f} → {thin:.2f}%"

    return figure


def _novel_pose_gap_range(region: str) -> Callable[[Path], str]:
    def figure(results: Path) -> str:
        gaps = novel_pose_gaps(results)
        means = sorted((gaps[split, region][1]["mean"] for split in NOVEL_POSE_SPLITS), reverse=True)
        return f"{_signed(means[0])} to {_signed(means[-1])}%"

    return figure


def _when(doc) -> str:
    commit = (doc.commit or "").replace("+dirty", "")[:7]
    return f"{doc.date[:16].replace('T', ' ')}Z" + (f" at {commit}" if commit else "")


def _verdict(met: bool) -> str:
    return "met" if met else "**not met**"


# The speed work's quality guard (``speed_quality/``): (setting, base, what the setting is).
SPEED_QUALITY = (
    ("detach", "exact", "the weight MLP's inputs detached"),
    ("lpips2", "exact", "LPIPS every 2nd step"),
    ("detach_lpips2", "exact", "both of the above"),
    ("bf16", "bf16_base", "the weight MLP in bfloat16"),
    ("lpips_late", "lpips_late_base", "LPIPS every 2nd step after densification"),
    ("mlp_width64", "mlp_width_base", "both MLPs 64 wide, not 128 (in `default`)"),
    ("mlp_width64_3dgs", "mlp_width_base_3dgs", "both MLPs 64 wide, not 128 (in `default`)"),
    ("conf_half", "mlp_width64", "the confidence network at half resolution"),
    ("knn_new", "knn_base", "initial scales from the exact nearest neighbours (reverted: `knn_novel_pose/`)"),
)
SPEED_QUALITY_CELLS = (  # (column, region or None, metric, lower is better)
    ("train time", None, "train_seconds", True),
    ("full LPIPS-VGG", "full", "lpips_vgg", True),
    ("hand LPIPS-VGG", "hand", "lpips_vgg", True),
    ("face LPIPS-VGG", "face", "lpips_vgg", True),
    ("full PSNR", "full", "psnr", False),
)


def seed_runs(folder: Path, name: str) -> tuple[str, dict[str, dict[int, dict]]]:
    """(preset, {method: {seed: run entry}}) of ``bench paper_tables``' ``<name>_seed*.json``."""
    doc = load_seeds(folder, name)
    return doc["config"]["preset"], runs_by_seed(doc)


def speed_quality(results: Path) -> list[str]:
    """Every training change the speed work measured against its base, paired over seeds
    (``docs/speed.md``, "Quality guard"; ``compare_settings``' gaps, one row per setting)."""
    folder = results / "speed_quality"
    lines = [
        "| setting | against | method, preset | "
        + " | ".join(column for column, *_ in SPEED_QUALITY_CELLS)
        + " | files |",
        "|---|---|---|" + "---:|" * len(SPEED_QUALITY_CELLS) + "---|",
    ]
    for setting, base, what in SPEED_QUALITY:
        preset, mine = seed_runs(folder, setting)
        _, theirs = seed_runs(folder, base)
        for method in (m for m in mine if m in theirs):
            seeds = sorted(mine[method].keys() & theirs[method].keys())
            cells = []
            for _, region, metric, lower in SPEED_QUALITY_CELLS:
                values = [
                    [run[metric] if region is None else run[region][metric] for run in (a[s] for s in seeds)]
                    for a in (mine[method], theirs[method])
                ]
                verdict, gap = compare_paired(*values, lower)
                cells.append(f"{gap['mean']:+.1f} ± {gap['std']:.1f}%, {verdict}")
            lines.append(
                f"| {what} (`{setting}`) | `{base}` | {method}, `{preset}`, {len(seeds)} seeds | "
                + " | ".join(cells)
                + f" | `{setting}_seed*`, `{base}_seed*` |"
            )
    return lines


def speed_targets(results: Path) -> list[str]:
    """Issue 38's goals against the latest run of each (``docs/speed.md``, "Targets")."""
    sections = json.loads((results / "train.json").read_text())  # label -> one run
    train = {name: TrainRun.model_validate(sections[label]) for name, label in SPEED_TRAIN_RUNS.items()}
    trained = ", ".join(
        f"`{n}` {r.train_seconds:.1f} s ({r.num_gaussians:,} Gaussians)" for n, r in train.items()
    )
    labels = ", ".join(dict.fromkeys(f"`{label.split('@')[1]}`" for label in SPEED_TRAIN_RUNS.values()))
    real_name, video = SPEED_REAL_VIDEO
    real = load(RealVideos, real_name, results)
    fast = real.videos[video].methods
    fast_text = ", ".join(f"`{m}` {r.train_seconds:.0f} s" for m, r in fast.items())
    service = load(ServiceLatency, "service", results)
    # The runs in a row that service.json is one of (``service_latency/runs_<commit>/``, the same
    # commit): this VM's speed moves between runs more than the gap to either goal, so a goal is
    # judged by the median over them, and every run's value is shown.
    runs = [
        run
        for _, run in load_each(ServiceLatency, "service_latency/runs_*/run*", results)
        if run.commit == service.commit
    ] or [service]
    by_row = [{(r.varies, r.size, r.clients): r for r in run.rows} for run in runs]
    p50s = [rows["pose", 512, 1].p50_ms for rows in by_row]
    p50 = statistics.median(p50s)
    ratios = {
        (varies, size): [
            rows[varies, size, 16].throughput_rps / rows[varies, size, 1].throughput_rps for rows in by_row
        ]
        for varies, size, clients in by_row[-1]
        if clients == 1 and (varies, size, 16) in by_row[-1]
    }
    ratio_text = "; ".join(
        f"a new {varies}: "
        + ", ".join(
            f"{statistics.median(r):.2f}x at {size}² ({min(r):.2f}-{max(r):.2f})"
            for (v, size), r in ratios.items()
            if v == varies
        )
        for varies in dict.fromkeys(v for v, _ in ratios)
    )
    below = sum(x < 1.0 for r in ratios.values() for x in r)
    in_runs = f"the median of {len(runs)} run(s) in a row at this commit"
    suite = load(TestSuite, "test_suite", results)
    fresh = load(TestSuite, "test_suite_fresh_clone", results)
    # The fresh-clone runs kept beside it and made after it (of its code, or a later one): met
    # only when every one of them is. Runs from before it measured older code.
    later = load_each(TestSuite, "test_suite_runs/fresh_clone_run*", results)
    fresh_runs = [fresh, *(run for _, run in later if run.date > fresh.date)]
    fresh_met = all(r.exit_code == 0 and r.wall_seconds <= 300 for r in fresh_runs)
    fresh_walls = " and ".join(f"{r.wall_seconds:.0f} s" for r in fresh_runs)
    counts = ", ".join(f"{n} {k}" for k, n in fresh.counts.items() if k != "warnings")
    demo = load(FirstContact, "first_contact", results)
    steps = ", ".join(f"{k} {v:.0f} s" for k, v in demo.steps_seconds.items() if v >= 1)
    raster = load(Rasterizer, "rasterizer", results)
    raster_2t = next(t for t in raster.targets if t.startswith("2 threads: forward+backward"))
    return [
        "| target | measured | file |",
        "|---|---|---|",
        f"| training, `--preset default` (2,000 iterations at 512 px), 2 threads, ≤ 300 s for both "
        f"`default` and `eva` | {trained}; {_when(train['default'])}: "
        f"{_verdict(all(r.train_seconds <= 300 for r in train.values()))} | `train.md` ({labels}) |",
        f"| `--preset fast` on `{video}`, the real-video protocol, ≤ 60 s | {fast_text}; {_when(real)}: "
        f"{_verdict(all(r.train_seconds <= 60 for r in fast.values()))} | `{real_name}.md` |",
        f"| render endpoint p50, a new pose at 512², one client, ≤ 30 ms | {p50:.1f} ms, {in_runs} "
        f"({', '.join(f'{v:.1f}' for v in p50s)}; {sum(v > 30 for v in p50s)} over 30); {_when(service)}: "
        f"{_verdict(p50 <= 30)} | `service.md`, `service_latency/runs_*/` |",
        f"| 16 clients' throughput at least one client's | {in_runs} (its range): {ratio_text}; "
        f"{below} of {sum(map(len, ratios.values()))} row-runs under 1; {_when(service)}: "
        f"{_verdict(all(statistics.median(r) >= 1.0 for r in ratios.values()))} | `service.md`, "
        "`service_latency/runs_*/` |",
        "| a fresh clone's `make test` ≤ 5 min of wall time, the install included | "
        f"{fresh_walls} in {len(fresh_runs)} run(s) of it; the first: pytest {fresh.pytest_seconds:.0f} s "
        f"({counts or 'no pytest summary'}; exit code {fresh.exit_code}); {_when(fresh)}: "
        f"{_verdict(fresh_met)}. In a checkout with its venv and caches: {suite.wall_seconds:.0f} s; "
        f"{_when(suite)} | `test_suite_fresh_clone.md`, `test_suite_runs/`, `test_suite.md` |",
        f"| a fresh clone's `make demo` ≤ 3 min, system packages included | {demo.total_seconds:.0f} s "
        f"({steps}); {_when(demo)}: {_verdict(demo.exit_code == 0 and demo.total_seconds <= 180)} "
        "| `first_contact.md` |",
        f"| rasterizer, 20k Gaussians at 512², forward and backward ≤ 60 ms | {raster_2t}; {_when(raster)} "
        "| `rasterizer.md` |",
    ]


SECTIONS: dict[str, Callable[[Path], list[str]]] = {
    "baselines": baselines,
    "baselines_real": baselines_real,
    "blink_sweep": blink_sweep,
    "wide_sweep": wide_sweep,
    "per_frame_hands": per_frame_hands,
    "region_sensitivity": region_sensitivity,
    "real_videos_expr": real_videos_change("real_videos_expr"),
    "real_videos_sil": real_videos_change("real_videos_sil"),
    "real_videos_fz": real_videos_change("real_videos_fz"),
    "real_videos_fb": real_videos_change("real_videos_fb", psnr=True),
    "real_videos_ssim_vs_bs": real_videos_change(
        "real_videos_ssim_vs_bs", labels=("λ_s = 0.01 (paper)", "λ_s = 0.2")
    ),
    "real_video_hands": real_video_hands,
    "closeup_views": face_changes(
        "mean ± std, 3 seeds (gap: per seed)",
        ("frames only", "with close-ups"),
        "expressions/closeups/closeup_{clip}_paired",
        None,
        (
            ("close-up LPIPS-VGG ×1000", "openings", "lpips_vgg"),
            ("close-up PSNR", "openings", "psnr"),
            *((f"close-up {label}", source, key) for label, source, key in OPENING_ROWS),
        ),
    ),
    "closeup_frames": face_changes(
        "at 512 px, mean ± std, 3 seeds",
        ("frames only", "with close-ups"),
        "expressions/closeups/frame_{clip}_paired",
        "expressions/closeups/eval_closeups_{clip}",
        (
            *OPENING_ROWS,
            ("face LPIPS-VGG ×1000", "eval", "face.lpips_vgg"),
            ("face PSNR", "eval", "face.psnr"),
            ("full LPIPS-VGG ×1000", "eval", "full.lpips_vgg"),
            ("full PSNR", "eval", "full.psnr"),
            ("face LPIPS-Alex ×1000 (trained on)", "eval", "face.lpips_alex"),
        ),
    ),
    **clips_and_driving(
        "colour_spread",
        ("default", "spread 6 mm"),
        "expressions/colour_spread/{clip}_spread_local_paired",
        "expressions/colour_spread/eval_{clip}_spread_local",
    ),
    "smoothing_stages": smoothing_stages,
    "speed_quality": speed_quality,
    "real_videos_history": real_videos_history,
    "body_prior": body_prior,
    "region_terms": region_terms,
    "attach_by_piece": attach_variants(
        (
            (
                "before (`expressions_after.md`)",
                "expressions/expressions_after",
                "expressions/real_videos_pieces",
                "before",
            ),
            (
                "pieces (`expressions_pieces.md`)",
                "expressions/expressions_pieces",
                "expressions/real_videos_pieces",
                "after",
            ),
        ),
        ("eyes", "face"),
    ),
    "skin_frames": attach_variants(
        (
            (
                "offsets only (before)",
                "expressions/expressions_after",
                "expressions/real_videos_frames",
                "before",
            ),
            (
                "a: frames, all levered",
                "expressions/expressions_frames",
                "expressions/real_videos_frames",
                "after",
            ),
            (
                "b: frames, none levered",
                "expressions/expressions_frames_b",
                "expressions/real_videos_frames_b",
                "after",
            ),
            (
                "d: frames, levered within 1 cm (the product)",
                "expressions/expressions_frames_d",
                "expressions/real_videos_frames_d",
                "after",
            ),
        ),
        ("eyes", "mouth", "face", "face_change", "driving"),
    ),
    "opening_term": opening_term,
    "opening_stages": opening_stages,
    "outline_real": real_videos_regions("outline_real/compare"),
    "body_prior_real": real_videos_regions("body_prior/compare"),
    "thin_term_face": render_openings(
        "product", {"expressions/face_views/expressions_thin:no_thin": "without the thin term"}
    ),
    "thin_term_face_relaxed": render_openings(
        "product",
        {
            "expressions/face_views/expressions_face_thin_02:face_thin_02": "face weight 0.2",
            "expressions/face_views/expressions_face_target_1cm:face_target_1cm": "face free to 1 cm",
            "expressions/face_views/expressions_face_thin_off:face_thin_off": "face weight 0",
        },
    ),
    "calibration_videos": face_variants(
        "expressions/calibration/{clip}_paired_{variant}",
        "expressions/calibration/eval_{clip}_{variant}",
        {"calib": "every landmark calibrated", "noeyes": "this tree (eye outlines not)"},
        (
            ("render: mouth r", "openings", "mouth_r"),
            ("render: mouth range over the target's", "openings", "mouth_range"),
            ("render: eyes r", "openings", "eyes_r"),
            ("render: eyes range over the target's", "openings", "eyes_range"),
            *LPIPS_ROWS,
        ),
    ),
    "colour_rate": face_variants(
        "expressions/colour_rate/{clip}_{variant}_paired",
        "expressions/colour_rate/eval_{clip}_{variant}",
        {"lr3": "rate 0.02", "lr10": "rate 0.0067", "lr3ev": "rate 0.02, blink frames 3 more times"},
        (
            ("render: mouth r", "openings", "mouth_r"),
            ("render: mouth range over the target's", "openings", "mouth_range"),
            ("render: eyes r", "openings", "eyes_r"),
            ("render: eyes range over the target's", "openings", "eyes_range"),
            *LPIPS_ROWS,
        ),
    ),
    "expression_colours": face_changes(
        "mean ± std, 3 seeds (gap: per seed)",
        ("rest colours", "expression colours"),
        "expressions/colours/{clip}_paired",
        "expressions/colours/eval_{clip}",
        (
            *OPENING_ROWS,
            *LPIPS_ROWS,
            ("face PSNR", "eval", "face.psnr"),
        ),
    ),
    "blink_colours": face_changes(
        "mean ± std, 3 seeds",
        ("rest colours", "blink colours"),
        "expressions/colours/blinks/{clip}_paired",
        "expressions/colours/blinks/eval_{clip}",
        (
            *OPENING_ROWS,
            *LPIPS_ROWS,
        ),
    ),
    "novel_pose_splits": novel_pose_splits,
    "novel_pose_candidates": novel_pose_candidates,
    "novel_pose_before_after": novel_pose_before_after,
    "novel_pose_goals": novel_pose_goals,
    "novel_pose_closeups": novel_pose_closeups,
    "novel_pose_filters": novel_pose_filters,
    "novel_pose_lid_ridge": novel_pose_lid_ridge,
    "paper_tables": paper_tables,
    "paper_regime": paper_regime,
    "service_latency": service_latency,
    "calibration_wild": calibration_wild,
    "calibration_draws": calibration_draws,
    "expression_range_fits": expression_range_fits,
    "expression_range_stages": expression_range_stages,
    **clips_and_driving(
        "expression_range",
        ("before", "in range"),
        "expressions/bounded/{clip}_bounded_paired",
        "expressions/bounded/eval_{clip}_bounded",
    ),
    **clips_and_driving(
        "eye_binding",
        ("default", "median face, eyes bound"),
        "expressions/eye_binding/{clip}_mb_paired",
        "expressions/eye_binding/eval_{clip}_mb",
    ),
    "lid_colours": face_variants(
        "expressions/lid_colours/{clip}_{variant}_paired",
        "expressions/lid_colours/eval_{clip}_{variant}",
        {
            "lid4": "+ eyeWide",
            "lid6": "+ eyeWide, eyeSquint",
            "lid6h": "the same, half the rate",
            "lid6r": "the same, ridge 1e-3",
        },
        (*OPENING_ROWS_FULL, *LPIPS_ROWS),
    ),
    **clips_and_driving(
        "training_length",
        ("fast", "default preset"),
        "expressions/preset/{clip}_dp_paired",
        "expressions/preset/eval_{clip}_dp",
        OPENING_ROWS_FULL,
    ),
    "closeup_densify": closeup_densify,
    "face_goal": face_goal,
    **clips_and_driving(
        "closeups_default_preset",
        ("default preset", "with close-ups"),
        "expressions/closeup_preset/{clip}_dpc_paired",
        "expressions/closeup_preset/eval_{clip}_dpc",
        OPENING_ROWS_FULL,
    ),
    "speed_targets": speed_targets,
    "align_measurements": align_measurements,
    "time_to_quality": time_to_quality,
}


def _eva_vs_3dgs_hands(results: Path) -> dict[str, MetricChange]:
    """eva against 3dgs+body on the gesturing LatentSync clip, paired by seed: region -> its
    LPIPS-VGG change (``real_videos_hands/eva_vs_3dgs``)."""
    (video,) = load(RealVideosCompare, "real_videos_hands/eva_vs_3dgs", results).comparison.values()
    return {region: metrics["lpips_vgg"] for region, metrics in video.items()}


def _eva_vs_3dgs_hands_gap(region: str) -> Callable[[Path], str]:
    def figure(results: Path) -> str:
        g = _eva_vs_3dgs_hands(results)[region].gap_pct
        return _percent_gap(g.mean, g.std)

    return figure


def _eva_vs_3dgs_hands_cut_range(results: Path) -> str:
    cuts = sorted(-c.gap_pct.mean for c in _eva_vs_3dgs_hands(results).values())
    return f"{cuts[0]:.0f}-{cuts[-1]:.0f}%"


def _official_vs_3dgs_ratio(results: Path) -> str:
    """How many times 3dgs+body's LPIPS-VGG eva-official's is in the paper's regime, over the full
    image, the hands and the face (``paper_regime.json``, means over the seeds)."""
    doc = load(PaperTables, "paper_regime", results)
    official, base = doc.methods["eva-official"], doc.methods["3dgs+body"]
    ratios = sorted(
        getattr(official, region)["lpips_vgg"].mean / getattr(base, region)["lpips_vgg"].mean
        for region in ("full", "hand", "face")
    )
    return f"{ratios[0]:.1f}-{ratios[-1]:.1f}×"


def eval_gap(results: Path, name: str) -> str:
    """The figure ``eval_gap/<result>/<region>.<metric>``: that row's paired gap of an ``eva eval``
    comparison (``bench eval_compare``), e.g. ``eval_gap/expressions/events/eval_seated_events/
    full.psnr`` -> "−1.0 ± 0.6%"."""
    result, key = name.rsplit("/", 1)
    for row in load(EvalPaired, result, results).rows:
        if f"{row.region}.{row.metric}" == key:
            return _percent_gap(row.gap_percent.mean, row.gap_percent.std)
    raise KeyError(f"{result}.json has no row {key!r}")


def expr_gap(results: Path, name: str) -> str:
    """The figure ``expr_gap/<result>/<measure>``: that row's paired gap of a ``bench
    expressions_compare`` file, in % for a relative measure (LPIPS, PSNR) and in the measure's own
    units for an absolute one (a correlation, a range), e.g. ``expr_gap/expressions/closeups/
    closeup_seated_paired/lpips_vgg`` -> "−11.1 ± 0.4%"."""
    result, measure = name.rsplit("/", 1)
    for row in load(OpeningsPaired, result, results).rows:
        if row.measure == measure:
            if row.relative:
                return _percent_gap(row.gap.mean, row.gap.std)
            return f"{_signed(row.gap.mean, 2)} ± {row.gap.std:.2f}"
    raise KeyError(f"{result}.json has no row {measure!r}")


def novel_pose_span(results: Path, name: str) -> str:
    """The figure ``novel_pose_span/<result>/<row>/<debris|holes>``: the lowest and highest of a
    ``bench novel_pose`` row's split means, in %, e.g. "29-38%"."""
    result, row, key = name.rsplit("/", 2)
    splits = load(NovelPose, result, results).methods[row].splits.values()
    values = sorted(getattr(s, key).mean * 100 for s in splits)
    digits = 0 if values[0] >= 10 else 1
    return f"{values[0]:.{digits}f}-{values[-1]:.{digits}f}%"


def novel_pose_ratio(results: Path, name: str) -> str:
    """The figure ``novel_pose_ratio/<result>/<row>/<baseline>/<region>``: the lowest and highest
    over the splits of a row's LPIPS-VGG mean over the baseline's, e.g. "1.6-3.7×"."""
    result, row, baseline, region = name.rsplit("/", 3)
    methods = load(NovelPose, result, results).methods
    ratios = sorted(
        getattr(methods[row].splits[split], region)["lpips_vgg"].mean
        / getattr(methods[baseline].splits[split], region)["lpips_vgg"].mean
        for split in NOVEL_POSE_SPLITS
    )
    return f"{ratios[0]:.1f}-{ratios[-1]:.1f}×"


def _novel_pose_runs(results: Path, result: str, row: str) -> tuple[list[dict], dict]:
    doc = json.loads((results / f"{result}.json").read_text())
    return doc["methods"][row]["runs"], doc["config"]


def novel_pose_angle(results: Path, name: str) -> str:
    """The figure ``novel_pose_angle/<result>/<row>/<angle>.<lpips_vgg|debris>``: the view split
    at one camera angle (``bench.novel_pose.view_breakdown``), LPIPS-VGG ×1000 or debris in %."""
    result, row, key = name.rsplit("/", 2)
    angle, metric = key.split(".")
    v = view_breakdown(_novel_pose_runs(results, result, row)[0])[int(angle)][metric]
    return f"{v * 1000:.1f}" if metric == "lpips_vgg" else f"{v * 100:.2f}%"


def novel_pose_novelty(results: Path, name: str) -> str:
    """The figure ``novel_pose_novelty/<result>/<row>/<yaw_beyond|pose>/<bin start>.<lpips_vgg|debris>``:
    one bin of the quality-against-novelty table (``bench.novel_pose.by_novelty``), LPIPS-VGG
    ×1000 or debris in %."""
    result, row, table, key = name.rsplit("/", 3)
    start, metric = key.rsplit(".", 1)
    runs, config = _novel_pose_runs(results, result, row)
    train_yaw = {int(seed): yaw for seed, yaw in config["train_yaw_deg_by_seed"].items()}
    for b in by_novelty(runs, train_yaw)[table]:
        if b["bin"][0] == float(start):
            v = b[metric]
            return f"{v * 1000:.1f}" if metric == "lpips_vgg" else f"{v * 100:.1f}%"
    raise KeyError(f"{result}.json, {row}: no {table} bin starting at {start}")


PAPER_GAP = re.compile(
    r"(?P<a>.+?)@(?P<method_a>[\w+-]+)/(?P<b>.+?)@(?P<method_b>[\w+-]+)/(?P<region>\w+)(?:\.(?P<metric>\w+))?"
)


def _paper_runs(results: Path, name: str) -> dict[str, dict[int, dict]]:
    """{method: {seed: run}} of a ``bench paper_tables`` result: ``<name>.json``, else the union
    of its per-seed files ``<name>_seed*.json``."""
    file = results / f"{name}.json"
    if file.is_file():
        return runs_by_seed(json.loads(file.read_text()))
    docs = [json.loads(f.read_text()) for f in sorted(results.glob(f"{name}_seed*.json"))]
    if not docs:
        raise KeyError(f"no result {name}.json or {name}_seed*.json")
    return union_of_runs(docs)


def paper_gap(results: Path, name: str) -> str:
    """The figure ``paper_gap/<result>@<method>/<base result>@<base method>/<region>[.<metric>]``:
    one ``bench paper_tables`` method's runs against another's (the same or another file), paired
    by the seeds both ran, with the verdict (LPIPS-VGG unless ``metric``), e.g.
    ``paper_gap/novel_views_paper/thin@eva/paper_tables@eva/full`` -> "−14.8 ± 4.3% (better)"."""
    m = PAPER_GAP.fullmatch(name)
    if m is None:
        raise KeyError(
            f"paper_gap figure {name!r} is not <result>@<method>/<result>@<method>/<region>[.<metric>]"
        )
    metric = m["metric"] or "lpips_vgg"
    a = _paper_runs(results, m["a"])[m["method_a"]]
    b = _paper_runs(results, m["b"])[m["method_b"]]
    seeds = sorted(a.keys() & b.keys())
    verdict, g = compare_paired(
        [a[s][m["region"]][metric] for s in seeds],
        [b[s][m["region"]][metric] for s in seeds],
        lower_is_better=metric.startswith("lpips"),
    )
    if verdict == "too few seeds":
        return f"{_signed(g['mean'])}% (one seed)"
    return f"{_percent_gap(g['mean'], g['std'])} ({verdict})"


VALUE = re.compile(
    r"(?P<path>.+?)@(?P<digits>\d)(?P<sign>\+?)(?P<thousands>,?)(?:x(?P<scale>\d+))?(?P<percent>%?)"
)
# A list of numbers summed up by a last key of this name (``fit_iou/mean``).
SUMMARIES: dict[str, Callable[[list[float]], float]] = {
    "mean": statistics.fmean,
    "median": statistics.median,
    "min": min,
    "max": max,
}


def _leaves(node, keys: list[str], where: str) -> list:
    """The values at ``keys`` under ``node``: a list by its index, ``*`` every item of a list or
    value of a dict (``base_s*``: of the keys it matches); ``_`` stands for a key's spaces
    (``steps_seconds/pip_install``); a last key of ``SUMMARIES`` sums a list of numbers up. A key
    may hold slashes (train.json's "<dataset>/<preset>[/<method>]@<label>"): the longest run of
    parts that names one wins, as "<dataset>/<preset>" is a key of its own too."""
    if not keys:
        return [node]
    if "*" in keys[0]:
        if isinstance(node, dict):
            items = [v for k, v in node.items() if fnmatch.fnmatchcase(k.replace(" ", "_"), keys[0])]
        else:
            items = node if isinstance(node, list) and keys[0] == "*" else []
        if not items:
            raise KeyError(f"{where}: nothing under {keys[0]!r}")
        return [leaf for item in items for leaf in _leaves(item, keys[1:], where)]
    if len(keys) == 1 and keys[0] in SUMMARIES and isinstance(node, list) and node:
        return [SUMMARIES[keys[0]]([float(x) for x in node])]
    for take in range(len(keys), 0, -1):
        key = "/".join(keys[:take])
        if isinstance(node, list) and take == 1 and key.isdigit() and int(key) < len(node):
            return _leaves(node[int(key)], keys[take:], where)
        if isinstance(node, dict):
            named = {k.replace(" ", "_"): k for k in node} | {k: k for k in node}
            if key in named:
                return _leaves(node[named[key]], keys[take:], where)
    raise KeyError(f"{where} has no {'/'.join(keys)!r}")


def _numbers(results: Path, path: str) -> list[float]:
    """Every number ``<result>/<key>/...`` names (see ``value``). The result is the longest leading
    part of the path that names a ``.json`` under ``results``; a ``*`` in it takes every file."""
    parts = path.split("/")
    for cut in range(len(parts) - 1, 0, -1):
        files = sorted(f for f in results.glob("/".join(parts[:cut]) + ".json") if f.is_file())
        if files:
            break
    else:
        raise KeyError(f"figure path {path!r} names no result file")
    return [float(x) for f in files for x in _leaves(json.loads(f.read_text()), parts[cut:], f.name)]


def _one(results: Path, path: str) -> float:
    numbers = _numbers(results, path)
    if len(numbers) != 1:
        raise KeyError(f"figure path {path!r} names {len(numbers)} numbers, not one")
    return numbers[0]


def _text(number: float, spec: str) -> str:
    return format(number, spec).replace("-", "\u2212")


def value(results: Path, name: str) -> str:
    """The figure ``value/<result>/<key>/.../<key>@<digits>[+][,][x<scale>][%]``: one number of a
    result file, by its keys (a list by its index), times ``scale``, with ``digits`` decimals
    (``+``: signed either way; ``,``: thousands separated) and a true minus sign, e.g.
    ``value/expressions/bounded/fits/runs/5/expression_mm@2`` -> "2.95"; a last key ``mean``,
    ``median``, ``min`` or ``max`` sums up a list there. A ``*`` in the result's name (``run*``:
    the runs of a set) or as a key (every item of a list or dict there) takes them all, and the
    figure is their range as printed: "9.0–9.8" ("−0.9 to +2.5" when signed), one number when they
    print the same."""
    m = VALUE.fullmatch(name)
    if m is None:
        raise KeyError(f"value figure {name!r} is not <result>/<key>/...@<digits>[+][,][x<scale>][%]")
    numbers = sorted(x * int(m["scale"] or 1) for x in _numbers(results, m["path"]))
    spec = f"{m['sign']}{m['thousands']}.{m['digits']}f"
    low, high = _text(numbers[0], spec), _text(numbers[-1], spec)
    span = low if low == high else f"{low} to {high}" if m["sign"] else f"{low}\u2013{high}"
    return span + m["percent"]


def stat(results: Path, name: str) -> str:
    """The figure ``stat/<result>/<key>/...@<digits>[x<scale>]``: the mean ± sample standard
    deviation of every number the path names (``*`` over seeds or runs, as ``value``'s), e.g.
    ``stat/expressions/expressions_sampling/cases/base_s*/stages/render/eyes/range_ratio@2`` ->
    "0.51 ± 0.12"."""
    m = VALUE.fullmatch(name)
    if m is None or m["sign"] or m["thousands"] or m["percent"]:
        raise KeyError(f"stat figure {name!r} is not <result>/<key>/...@<digits>[x<scale>]")
    numbers = _numbers(results, m["path"])
    if len(numbers) < 2:
        raise KeyError(f"stat figure {name!r} names {len(numbers)} number, not a spread")
    return fmt(mean_std(numbers), scale=int(m["scale"] or 1), digits=int(m["digits"]))


TWO_VALUES = re.compile(r"(?P<a>.+?)~(?P<b>.+?)@(?P<digits>\d)(?:x(?P<scale>\d+))?")


def _two_numbers(results: Path, name: str, family: str) -> tuple[float, float, int, int]:
    """``<path a>~<path b>@<digits>[x<scale>]`` -> (a, b, digits, scale), each path as
    ``value``'s, naming one number."""
    m = TWO_VALUES.fullmatch(name)
    if m is None:
        raise KeyError(f"{family} figure {name!r} is not <path a>~<path b>@<digits>[x<scale>]")
    return _one(results, m["a"]), _one(results, m["b"]), int(m["digits"]), int(m["scale"] or 1)


def change(results: Path, name: str) -> str:
    """The figure ``change/<path a>~<path b>@<digits>``: a against b in percent, signed, e.g.
    ``change/closeup_levers/runs/3/truth/lpips_vgg~closeup_levers/runs/0/truth/lpips_vgg@1`` ->
    "+2.7%"."""
    a, b, digits, _ = _two_numbers(results, name, "change")
    return _text(100.0 * (a / b - 1.0), f"+.{digits}f") + "%"


def difference(results: Path, name: str) -> str:
    """The figure ``difference/<path a>~<path b>@<digits>[x<scale>]``: a minus b, times ``scale``,
    signed, e.g. "+5.9"."""
    a, b, digits, scale = _two_numbers(results, name, "difference")
    return _text((a - b) * scale, f"+.{digits}f")


def ratio(results: Path, name: str) -> str:
    """The figure ``ratio/<path a>~<path b>@<digits>``: a over b, e.g. "1.4"."""
    a, b, digits, _ = _two_numbers(results, name, "ratio")
    return _text(a / b, f".{digits}f")


FIGURES: dict[str, Callable[[Path], str]] = {
    **{f"novel_pose.{split}.full": _novel_pose_gap(split, "full") for split in NOVEL_POSE_SPLITS},
    "novel_pose.view.face": _novel_pose_gap("view", "face"),
    "novel_pose.view.full.cut": _novel_pose_cut("view", "full"),
    "novel_pose.view.debris.cut": _novel_pose_cut("view", "debris"),
    "novel_pose.arm.range": _novel_pose_gap_range("arm"),
    "novel_pose.debris.cut_range": _novel_pose_cut_range("debris"),
    "novel_pose.view.holes": _novel_pose_holes("view"),
    **{f"real_video_hands.eva_vs_3dgs.{r}": _eva_vs_3dgs_hands_gap(r) for r in ("full", "hand", "face")},
    "real_video_hands.eva_vs_3dgs.cut_range": _eva_vs_3dgs_hands_cut_range,
    "paper_regime.official_vs_3dgs": _official_vs_3dgs_ratio,
    "expression_range.fit_seconds": _bounded_fit_seconds,
}
# Figures named ``<family>/<argument>``: one function serves every result file of a kind.
FIGURE_FAMILIES: dict[str, Callable[[Path, str], str]] = {
    "eval_gap": eval_gap,
    "expr_gap": expr_gap,
    "value": value,
    "change": change,
    "stat": stat,
    "difference": difference,
    "ratio": ratio,
    "novel_pose_gap": novel_pose_gap,
    "novel_pose_span": novel_pose_span,
    "novel_pose_ratio": novel_pose_ratio,
    "novel_pose_angle": novel_pose_angle,
    "novel_pose_novelty": novel_pose_novelty,
    "paper_gap": paper_gap,
}


# ----------------------------------------------------------------------------- the docs


def doc_paths(root: Path = ROOT) -> list[Path]:
    return sorted({p for pattern in DOCS for p in root.glob(pattern)})


def render(text: str, results: Path, where: str = "") -> str:
    """``text`` with every ``bench report`` block rewritten from ``results``."""

    def fill(m: re.Match) -> str:
        name = m["name"]
        if name not in SECTIONS:
            raise KeyError(f"{where}: unknown bench report section {name!r} (known: {', '.join(SECTIONS)})")
        body = "\n".join(SECTIONS[name](results))
        return f"{m[1]}{body}\n{m[4]}"

    def figure(m: re.Match) -> str:
        name = m["name"]
        family, _, rest = name.partition("/")
        if rest and family in FIGURE_FAMILIES:
            return f"{m[1]}{FIGURE_FAMILIES[family](results, rest)}{m[4]}"
        if name not in FIGURES:
            raise KeyError(f"{where}: unknown bench figure {name!r}")
        return f"{m[1]}{FIGURES[name](results)}{m[4]}"

    return FIGURE.sub(figure, BLOCK.sub(fill, text))


def run(check: bool = False, root: Path = ROOT, results: Path = RESULTS) -> int:
    """Rewrite (or with ``check`` compare) every doc's blocks; 0 when all were current."""
    stale = []
    for path in doc_paths(root):
        text = path.read_text()
        if "<!-- bench report:" not in text and "<!-- bench figure:" not in text:
            continue
        new = render(text, results, where=str(path.relative_to(root)))
        if new != text:
            stale.append(path.relative_to(root))
            if not check:
                path.write_text(new)
    for path in stale:
        print(f"{path}: {'stale' if check else 'rewritten'} (python -m bench report)")
    return 1 if (check and stale) else 0
