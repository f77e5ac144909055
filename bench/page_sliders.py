"""How the web page's picture follows a slider that a person drags (issue 38, the renders).

Serves a copy of ``--service-dir`` (a service data folder with a finished avatar, e.g. the
demo's ``out/demo/service``) with ``eva serve``, opens the page in headless Chromium (Debian's
``chromium`` and ``chromedriver``, selenium) and drags sliders the way a hand does: the page's
script sets a slider's value and fires its ``input`` event every 16 ms (60 Hz) for
``--drag-seconds``, sweeping the slider out and back. The page records each picture it shows
(a ``MutationObserver`` on the image's render counter) with its time and size. Per drag:

- first picture: from the drag's first event to the first new picture on screen;
- pictures per second while the drag lasts, and the longest wait between two of them;
- settled: from the drag's last event to the last picture (the full-size image of the final
  slider values), and that picture's size.

    .venv/bin/python -m bench page_sliders --service-dir out/demo/service --name page_sliders \\
        --out bench/results/service_latency

Writes ``<name>.json`` and ``<name>.md``. Skips with a message where Chromium, chromedriver or
selenium are missing.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from bench.machine import write_result
from bench.serving import base_report, ensure_service_dir, header, ready_avatar, serve_only
from service.headless_browser import missing, start_chromium

DRAGS = (  # (label, CSS selector of the slider)
    ("left arm out", 'input[data-control="arm_out.L"]'),
    ("right elbow", 'input[data-control="elbow.R"]'),
    ("camera yaw", "#camera-yaw"),
)

RECORD = """
window.shown = [];
const img = document.getElementById("pose-image");
new MutationObserver(() => window.shown.push([performance.now(), img.naturalWidth, img.naturalHeight]))
  .observe(img, {attributes: true, attributeFilter: ["data-renders"]});
"""

# arguments[0]: the slider's selector; arguments[1]: the drag's length in ms.
DRAG = """
const input = document.querySelector(arguments[0]);
const lo = Number(input.min), hi = Number(input.max), steps = Math.round(arguments[1] / 16);
window.drag = {start: performance.now(), end: null};
let k = 0;
const timer = setInterval(() => {
  k += 1;
  input.value = String(lo + (hi - lo) * (0.5 + 0.45 * Math.sin(2 * Math.PI * k / steps)));
  input.dispatchEvent(new Event("input"));
  if (k >= steps) {
    clearInterval(timer);
    drag.end = performance.now();
  }
}, 16);
"""


def wait(driver, script: str, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.05)
    raise SystemExit(f"timed out after {timeout:.0f} s waiting for {what}")


def settled(driver, quiet_s: float = 1.5, timeout: float = 60.0) -> list:
    """The pictures shown, once none has come for ``quiet_s`` after the drag ended."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        shown, end = driver.execute_script("return [shown, drag.end]")
        if end is not None:
            count = len(shown)
            if last is not None and count == last[0] and time.monotonic() - last[1] >= quiet_s:
                return shown
            if last is None or count != last[0]:
                last = (count, time.monotonic())
        time.sleep(0.05)
    raise SystemExit("the page did not settle after the drag")


def measure_drag(driver, selector: str, drag_ms: float) -> dict:
    driver.execute_script("window.shown.length = 0")
    driver.execute_script(DRAG, selector, drag_ms)
    shown = settled(driver)
    start, end = driver.execute_script("return [drag.start, drag.end]")
    times = [t for t, _, _ in shown]
    during = [t for t in times if start <= t <= end]
    gaps = [b - a for a, b in zip([start, *during], during, strict=False)]
    last = shown[-1] if shown else (None, 0, 0)
    return {
        "first_picture_ms": (times[0] - start) if times else None,
        "pictures_during_drag": len(during),
        "pictures_per_s": len(during) / ((end - start) / 1000.0),
        "longest_wait_ms": max([*gaps, (end - during[-1]) if during else end - start]),
        "settled_ms": (times[-1] - end) if times else None,
        "last_picture_px": [last[1], last[2]],
        "pictures": len(shown),
    }


def run(args) -> dict:
    work = Path(tempfile.mkdtemp(prefix="eva-bench-page-"))
    data = ensure_service_dir(args.service_dir, work)
    stack = serve_only(data, work / "logs")
    driver = profile = None
    try:
        avatar = ready_avatar(stack.base_url, {})
        driver, profile = start_chromium()
        driver.get(f"{stack.base_url}/")
        card = f'.avatar-card[data-avatar-id="{avatar["avatar_id"]}"]'
        wait(driver, f"return document.querySelector('{card}')", 60, "the avatar's card")
        driver.execute_script(f"document.querySelector('{card}').click()")
        wait(
            driver,
            "const i = document.getElementById('pose-image');"
            "return Number(i.dataset.renders) >= 1 && !state.rendering",
            120,
            "the first render",
        )
        time.sleep(1.0)
        driver.execute_script(RECORD)
        rows = []
        for repeat in range(args.repeats):
            for label, selector in DRAGS:
                if not driver.execute_script("return !!document.querySelector(arguments[0])", selector):
                    raise SystemExit(f"the page has no slider {selector}")
                row = measure_drag(driver, selector, 1000.0 * args.drag_seconds)
                rows.append({"slider": label, "repeat": repeat, **row})
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    finally:
        if driver is not None:
            driver.quit()
        if profile:
            shutil.rmtree(profile, ignore_errors=True)
        stack.close()
        shutil.rmtree(work, ignore_errors=True)
    return {
        **base_report(args),
        "avatar": {"num_gaussians": avatar.get("num_gaussians"), "preset": avatar.get("preset")},
        "drag_seconds": args.drag_seconds,
        "rows": rows,
        "summary": summary(rows),
    }


def summary(rows: list[dict]) -> dict:
    def med(key):
        values = [r[key] for r in rows if r[key] is not None]
        return statistics.median(values) if values else None

    return {
        key: med(key) for key in ("first_picture_ms", "pictures_per_s", "longest_wait_ms", "settled_ms")
    } | {"all_settled_full_size": all(r["last_picture_px"] == [360, 420] for r in rows)}


def write(report: dict, out: Path, name: str) -> None:
    lines = header("The page's picture under a dragged slider", report, report.get("note")) + [
        f"- avatar: {report['avatar']['num_gaussians']} Gaussians ({report['avatar']['preset']} preset); "
        f"headless Chromium on the same machine as the service; each drag {report['drag_seconds']:g} s of "
        "`input` events at 60 Hz",
        "",
        "| slider | repeat | first picture ms | pictures/s while dragging | longest wait ms | settled ms "
        "| last picture |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for r in report["rows"]:
        lines.append(
            f"| {r['slider']} | {r['repeat']} | {r['first_picture_ms']:.0f} | {r['pictures_per_s']:.1f} "
            f"| {r['longest_wait_ms']:.0f} | {r['settled_ms']:.0f} | {r['last_picture_px'][0]}x"
            f"{r['last_picture_px'][1]} |"
        )
    s = report["summary"]
    lines += [
        "",
        f"Medians: first picture {s['first_picture_ms']:.0f} ms, {s['pictures_per_s']:.1f} pictures/s "
        f"while dragging, longest wait {s['longest_wait_ms']:.0f} ms, settled {s['settled_ms']:.0f} ms "
        f"after the last event; every drag ends on the full-size image: {s['all_settled_full_size']}.",
    ]
    write_result(out, name, report, lines)
    print(f"wrote {out / name}.{{json,md}}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--service-dir", type=Path, default=None)
    ap.add_argument("--drag-seconds", type=float, default=3.0)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--note", default=None)
    ap.add_argument("--name", default="page_sliders")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = ap.parse_args(argv)
    if reason := missing():
        raise SystemExit(f"skipped: {reason}")
    write(run(args), args.out, args.name)


if __name__ == "__main__":
    main()
