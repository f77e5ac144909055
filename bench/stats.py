"""Mean ± std over seeds, and the rules for stating a finding: a gap counts only when it exceeds
its noise, otherwise it is "no difference". Unpaired (two rows): the combined standard
deviation sqrt(std_a² + std_b²). Paired (two methods on the same seeds, i.e. the same subjects
and training seeds): the per-seed relative gaps, whose mean must exceed their standard
deviation; subjects differ more from each other than methods do, so this is the fairer test."""

from __future__ import annotations

import math
import statistics


def mean_std(values: list[float]) -> dict[str, float]:
    """{"mean", "std", "n"}: the sample standard deviation (0 for one value)."""
    if not values:
        raise ValueError("no values")
    if len(values) < 2:
        std = 0.0
    elif all(math.isfinite(v) for v in values):
        std = statistics.stdev(values)
    else:  # a gap against a zero: no spread to speak of, and no verdict either
        std = math.inf
    return {"mean": statistics.fmean(values), "std": std, "n": len(values)}


def fmt(stat: dict[str, float], scale: float = 1.0, digits: int = 2) -> str:
    """'12.34 ± 0.56' (values times ``scale``)."""
    return f"{scale * stat['mean']:.{digits}f} ± {scale * stat['std']:.{digits}f}"


def compare(a: dict[str, float], b: dict[str, float], lower_is_better: bool) -> tuple[str, float]:
    """("better" | "worse" | "no difference", relative gap of a against b in %) for two
    ``mean_std`` rows: better/worse only when |mean_a - mean_b| > sqrt(std_a² + std_b²)."""
    gap = a["mean"] - b["mean"]
    rel = 100.0 * gap / abs(b["mean"]) if b["mean"] else math.inf
    if abs(gap) <= math.hypot(a["std"], b["std"]):
        return "no difference", rel
    improved = gap < 0 if lower_is_better else gap > 0
    return ("better" if improved else "worse"), rel


def compare_paired(a: list[float], b: list[float], lower_is_better: bool) -> tuple[str, dict[str, float]]:
    """("better" | "worse" | "no difference" | "too few seeds", mean_std of the per-seed
    relative gaps of a against b in %) for the values of two methods on the same seeds, in the
    same order. Better/worse only when |mean gap| > std of the gaps, with at least 2 seeds."""
    if len(a) != len(b) or not a:
        raise ValueError("paired values need the same, non-zero number of seeds")
    gaps = mean_std(
        [0.0 if x == y else 100.0 * (x - y) / abs(y) if y else math.inf for x, y in zip(a, b, strict=True)]
    )
    if len(a) < 2:
        return "too few seeds", gaps
    if abs(gaps["mean"]) <= gaps["std"]:
        return "no difference", gaps
    improved = gaps["mean"] < 0 if lower_is_better else gaps["mean"] > 0
    return ("better" if improved else "worse"), gaps


def zero_crossing(values: list[float], gaps: list[float]) -> float | None:
    """The value where ``gaps`` (sampled at ``values``) first falls from above zero to zero or
    below (linear between samples, 3 decimals), else None: e.g. the blink that closes a lid gap."""
    points = list(zip(values, gaps, strict=True))
    for (v0, g0), (v1, g1) in zip(points, points[1:], strict=False):
        if g0 > 0 >= g1:
            return round(v0 + (v1 - v0) * g0 / (g0 - g1), 3)
    return None
