"""Render-endpoint latency of the service: p50/p95 at 256^2 and 512^2, 1 and 16 concurrent clients.

    .venv/bin/python bench/service.py --service-dir out/demo/service     # an existing service folder
    .venv/bin/python bench/service.py                                    # makes one with `eva demo`

A real ``eva serve`` on a free loopback port renders an avatar of the service folder; clients
POST ``/avatars/{id}/render`` with a new pose (a different pose per request, so nothing can be
cached) and time the whole HTTP round trip. Target: p50 <= 100 ms at 512^2 on 2 cores.
Writes bench/results/service.json and service.md.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from machine import describe

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
EVA = str(Path(sys.executable).parent / "eva")


def ensure_service_dir(service_dir: Path | None) -> Path:
    if service_dir is not None:
        return service_dir
    work = Path(tempfile.mkdtemp(prefix="eva-bench-service-"))
    subprocess.run(
        [EVA, "demo", "--out", str(work / "demo.png"), "--workdir", str(work / "demo"), "--preset", "tiny"],
        check=True,
    )
    return work / "demo" / "service"


def measure(base: str, avatar_id: str, size: int, clients: int, requests_per_client: int) -> dict:
    import httpx

    latencies: list[float] = []
    errors: list[str] = []
    lock = threading.Lock()

    def client(k: int) -> None:
        with httpx.Client(base_url=base, timeout=120.0) as api:
            for i in range(requests_per_client):
                angle = 0.05 * ((k * requests_per_client + i) % 30)
                body = {
                    "pose": {
                        "joints": {"upperarm01.L": [0.0, 0.0, -0.6 - angle]},
                        "expression": {"jawOpen": angle},
                    },
                    "camera": {"yaw": 10.0 * angle},
                    "width": size,
                    "height": size,
                }
                t0 = time.perf_counter()
                r = api.post(f"/avatars/{avatar_id}/render", json=body)
                elapsed = time.perf_counter() - t0
                with lock:
                    if r.status_code == 200:
                        latencies.append(elapsed)
                    else:
                        errors.append(f"{r.status_code} {r.text[:120]}")

    started = time.perf_counter()
    threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - started
    q = statistics.quantiles(latencies, n=20) if len(latencies) >= 2 else [float("nan")] * 19
    return {
        "size": size,
        "clients": clients,
        "requests": len(latencies),
        "errors": errors[:5],
        "p50_ms": 1e3 * statistics.median(latencies),
        "p95_ms": 1e3 * q[18],
        "throughput_rps": len(latencies) / wall,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--service-dir", type=Path, help="a service data folder holding a finished avatar")
    parser.add_argument("--requests", type=int, default=20, help="requests per client")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()

    import httpx

    service_dir = ensure_service_dir(args.service_dir)
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = subprocess.Popen(
        [EVA, "serve", "--port", str(port), "--data-dir", str(service_dir), "--log-level", "warning"]
    )
    try:
        deadline = time.time() + 180
        while True:
            try:
                if httpx.get(f"{base}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.time() > deadline or server.poll() is not None:
                raise SystemExit("eva serve did not start")
            time.sleep(0.3)
        avatars = [a for a in httpx.get(f"{base}/avatars").json()["avatars"] if a["status"] == "ready"]
        if not avatars:
            raise SystemExit(f"no finished avatar in {service_dir}")
        avatar = avatars[-1]
        measure(base, avatar["avatar_id"], 64, 1, 2)  # load the avatar and warm up
        rows = [
            measure(base, avatar["avatar_id"], size, clients, max(2, args.requests // max(1, clients // 4)))
            for size in (256, 512)
            for clients in (1, 16)
        ]
    finally:
        server.terminate()
        server.wait(timeout=30)
    report = {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "command": "python bench/service.py " + " ".join(sys.argv[1:]),
        "machine": describe(),
        "avatar": {"num_gaussians": avatar.get("num_gaussians"), "preset": avatar.get("preset")},
        "rows": rows,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "service.json").write_text(json.dumps(report, indent=1))
    lines = [
        "# Service render latency",
        "",
        f"- date: {report['date']}",
        f"- command: `{report['command']}`",
        f"- machine: {report['machine']}",
        f"- avatar: {avatar.get('num_gaussians')} Gaussians ({avatar.get('preset')} preset); round trip over "
        "loopback HTTP incl. pose JSON validation, skinning, rasterization and PNG encoding",
        "",
        "| image | clients | requests | p50 ms | p95 ms | requests/s |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['size']}² | {r['clients']} | {r['requests']} | {r['p50_ms']:.0f} | {r['p95_ms']:.0f} "
            f"| {r['throughput_rps']:.1f} |"
        )
    p50 = next(r["p50_ms"] for r in rows if r["size"] == 512 and r["clients"] == 1)
    lines += [
        "",
        f"Target p50 <= 100 ms at 512² (1 client): {p50:.0f} ms ({'met' if p50 <= 100 else 'NOT met'}).",
    ]
    (args.out / "service.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


if __name__ == "__main__":
    main()
