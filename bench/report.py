"""``python -m bench report``: the tables the docs include, written from the result files.

A doc includes a table between two markers; everything between them is this module's output:

    <!-- bench report: paper_tables -->
    | | full | hand | face | N-GS |
    ...
    <!-- /bench report -->

``report --check`` fails when a doc's table is not what the committed results give (a test runs
it), so a figure in those tables cannot drift from its file. Each section reads its result through
a pydantic model of the fields it uses: a result whose shape changed fails loudly here, not as a
wrong number in the docs.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

from pydantic import BaseModel, ConfigDict

from bench.stats import fmt, mean_std

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
DOCS = ("README.md", "docs/*.md")
BLOCK = re.compile(r"(<!-- bench report: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /bench report -->)", re.S)


# ----------------------------------------------------------------------------- result shapes


class _Loose(BaseModel):
    model_config = ConfigDict(extra="ignore")


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


class ServiceLatency(_Loose):
    """``bench.serving latency``'s result."""

    date: str
    machine: str
    rows: list[LatencyRow]


def load(model: type[BaseModel], name: str, results: Path) -> BaseModel:
    return model.model_validate_json((results / f"{name}.json").read_text())


# ----------------------------------------------------------------------------- sections


def _mean_std(stat: Stat, scale: float = 1e3) -> str:
    if stat.n < 2:
        return f"{stat.mean * scale:.1f}"
    return f"{stat.mean * scale:.1f} ± {stat.std * scale:.1f}"


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


class AlignSynthetic(_Loose):
    fitted: AlignFit
    openings: dict[str, dict[str, Agreement]]


class AlignResult(_Loose):
    """``bench.align``'s result (the synthetic section)."""

    synthetic: AlignSynthetic


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


SECTIONS: dict[str, Callable[[Path], list[str]]] = {
    "paper_tables": paper_tables,
    "paper_regime": paper_regime,
    "service_latency": service_latency,
    "calibration_wild": calibration_wild,
    "closeup_densify": closeup_densify,
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

    return BLOCK.sub(fill, text)


def run(check: bool = False, root: Path = ROOT, results: Path = RESULTS) -> int:
    """Rewrite (or with ``check`` compare) every doc's blocks; 0 when all were current."""
    stale = []
    for path in doc_paths(root):
        text = path.read_text()
        if "<!-- bench report:" not in text:
            continue
        new = render(text, results, where=str(path.relative_to(root)))
        if new != text:
            stale.append(path.relative_to(root))
            if not check:
                path.write_text(new)
    for path in stale:
        print(f"{path}: {'stale' if check else 'rewritten'} (python -m bench report)")
    return 1 if (check and stale) else 0
