"""The Anny cache built in fresh folders with anny's own target loader and with
``eva_engine.body.anny_targets``' (alternately, ``--runs`` times each), its wall time, the share
of anny's loader in it (cProfile's cumulative ``load_blend_shape``, in a run of its own), and
whether the two builds' tensors are equal. ``python anny_build.py [--runs 2]`` from the repository,
nothing else running; it prints the Markdown table that ``anny_build.md`` holds."""

import argparse
import contextlib
import cProfile
import pstats
import tempfile
import time
from pathlib import Path

import anny
import torch
from safetensors.torch import load_file

from eva_engine.body.anny_cache import ANNY_MODEL_KWARGS, anny_cache_path
from eva_engine.body.anny_targets import faster_target_reader


def build(reader) -> tuple[float, dict[str, torch.Tensor]]:
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        with anny_cache_path(Path(folder)), reader():
            anny.Anny(**ANNY_MODEL_KWARGS)
        seconds = time.perf_counter() - started
        (compact,) = Path(folder).rglob("build_compact_model_data_*.safetensors")
        return seconds, load_file(str(compact))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=2)
    args = parser.parse_args()
    readers = {"anny's loader": contextlib.nullcontext, "anny_targets": faster_target_reader}
    times: dict[str, list[float]] = {name: [] for name in readers}
    tensors = {}
    for _ in range(args.runs):
        for name, reader in readers.items():
            seconds, tensors[name] = build(reader)
            times[name].append(seconds)
    a, b = tensors.values()
    equal = sorted(a) == sorted(b) and all(torch.equal(a[k], b[k]) for k in a)
    profile = cProfile.Profile()
    profile.runcall(build, contextlib.nullcontext)
    loader = next(
        row[3]  # cumulative seconds
        for func, row in pstats.Stats(profile).stats.items()
        if func[2] == "load_blend_shape"
    )
    print("| reader | builds (s) |\n|---|---|")
    for name, values in times.items():
        print(f"| {name} | {', '.join(f'{v:.1f}' for v in values)} |")
    print(f"\nanny's load_blend_shape under cProfile: {loader:.1f} s of the build; tensors equal: {equal}")


if __name__ == "__main__":
    main()
