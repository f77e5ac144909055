"""Mean ± std over seeds, and the rule for stating a finding: a gap counts only when it exceeds
the combined standard deviation of the two rows, sqrt(std_a² + std_b²); otherwise it is "no
difference"."""

from __future__ import annotations

import math
import statistics


def mean_std(values: list[float]) -> dict[str, float]:
    """{"mean", "std", "n"}: the sample standard deviation (0 for one value)."""
    if not values:
        raise ValueError("no values")
    std = statistics.stdev(values) if len(values) > 1 else 0.0
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
