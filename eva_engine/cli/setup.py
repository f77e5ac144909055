"""``eva setup``: one-time install steps (body-model cache, offline LPIPS weights)."""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import typer
from rich.console import Console

from eva_engine.cli.app import app


@app.command()
def setup(
    force: bool = typer.Option(
        False, "--force", help="Rebuild the Anny cache even if it is current; retry a failed kernel build."
    ),
    cache_dir: Path = typer.Option(None, help="Anny cache folder (default: <data dir>/cache/anny)."),
) -> None:
    """Build the Anny body-model cache (once, ~10 s); read the face mesh's correspondence and
    calibration shipped with the package, or build them where the installed body model or
    MediaPipe differs from theirs (MediaPipe on rendered faces, ~40 s); build the C++ kernels of
    the rasterizer and the skinning (~10 s); and check the offline LPIPS weights."""
    from eva_engine.body import load_body_model, prepare_anny_cache
    from eva_engine.metrics import LPIPSWeightsError, prepare_lpips

    console = Console(stderr=True)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    started = time.perf_counter()
    with console.status("Anny body-model cache (first build takes about 10 s)..."):
        path = prepare_anny_cache(cache_dir, force=force)
        model = load_body_model("anny", cache_dir=path, build_cache=False)
    # The kernels compile after the Anny build (beside it they halved its pace), beside the face
    # mesh's files, which are read (shipped) or built (bench/results/first_contact_setup/).
    # cpp_extension imported here, before the threads: its import (setuptools, which puts its
    # vendored packages on the path) raced with other imports and failed a build now and then
    # ("No module named 'jaraco'", bench/results/first_contact_setup/shipped_face_files.md).
    from torch.utils import cpp_extension  # noqa: F401

    from eva_engine.avatar.skinning import SKINNING
    from eva_engine.render.native import RASTER

    # One compiler each: a compiler keeps one core busy, and with the face-mesh files shipped
    # little else runs beside them.
    compilers = ThreadPoolExecutor(max_workers=2)
    kernels = [compilers.submit(_build_kernel, library, force) for library in (RASTER, SKINNING)]
    compilers.shutdown(wait=False)
    console.print(
        f"[green]ok[/] Anny cache {path}: {model.num_vertices} vertices, {model.num_joints} joints, "
        f"{len(model.expression_names)} expressions ({time.perf_counter() - started:.0f} s)"
    )
    _face_mesh_files(console, model, path)
    with console.status("C++ kernels (compiled once per machine)..."):
        built = [kernel.result() for kernel in kernels]
    for library, ops, seconds in built:
        if ops is None:
            # Not fatal: the torch kernels give the same results, only slower.
            console.print(
                f"[yellow]warning[/] {library.what} C++ kernels unavailable, torch kernels in use: "
                f"{library.unavailable_reason()}"
            )
        else:
            console.print(
                f"[green]ok[/] {library.what} C++ kernels ({seconds:.0f} s, beside the steps above)"
            )
    try:
        weights = prepare_lpips()
    except LPIPSWeightsError as err:
        console.print(f"[red]error[/] LPIPS weights: {err}")
        raise typer.Exit(1) from err
    console.print("[green]ok[/] LPIPS weights " + ", ".join(f"{k}: {v}" for k, v in weights.items()))


def _face_mesh_files(console: Console, model, path: Path) -> None:
    """The face mesh's correspondence and calibration, built from one painted-face renderer."""
    from eva_engine.align.face_calibration import load_calibration
    from eva_engine.align.face_mesh import load_correspondence, shared_painted_face

    with shared_painted_face(model) as renderer:
        started = time.perf_counter()
        with console.status("face-mesh correspondence (MediaPipe on rendered faces)..."):
            corr = load_correspondence(model, cache_dir=path, renderer=renderer)
        if corr is None:
            console.print("[yellow]warning[/] no face-mesh correspondence: dense face fitting is off")
            return
        console.print(
            f"[green]ok[/] face-mesh correspondence: {int(corr.valid.sum())} of {len(corr.valid)} landmarks "
            f"({time.perf_counter() - started:.0f} s)"
        )
        started = time.perf_counter()
        with console.status("face-mesh calibration (MediaPipe on faces with expressions)..."):
            calibration = load_calibration(model, corr, cache_dir=path, renderer=renderer)
    if calibration is None:
        console.print(
            "[yellow]warning[/] no face-mesh calibration: the fit compares the correspondence alone"
        )
    else:
        console.print(
            f"[green]ok[/] face-mesh calibration: {len(calibration.landmarks)} landmarks, "
            f"{calibration.gain.shape[0]} facial actions ({time.perf_counter() - started:.0f} s)"
        )


def _build_kernel(library, force: bool) -> tuple[object, object, float]:
    """Compile (or load) one library of C++ kernels: (library, its ops or None, seconds)."""
    started = time.perf_counter()
    ops = library.load(force=force)
    return library, ops, time.perf_counter() - started
