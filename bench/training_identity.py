"""Whether a change leaves training bit-identical: a fingerprint (SHA-256 of every saved tensor)
of short trainings, to compare between two checkouts of the repository.

    .venv/bin/eva synth --preset controlled --size small --seed 0 --out /tmp/ident-ds
    .venv/bin/python -m bench training_identity /tmp/ident-ds > after.json
    cd ../other-checkout  # e.g. `git worktree add ../other-checkout <commit>`
    PYTHONPATH=. ../main/.venv/bin/python ../main/bench/training_identity.py /tmp/ident-ds > before.json

Each method trains ``--iterations`` steps of the ``fast`` preset (170 by default: two
densification events) at one thread, seed 0; equal fingerprints mean equal avatars, so every
benchmark of those methods is unchanged. Prints JSON: {method: {"gaussians", "sha256"}}.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json

import torch


def fingerprint(state: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for key in sorted(state):
        h.update(key.encode())
        h.update(state[key].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--iterations", type=int, default=170)
    ap.add_argument(
        "--methods", nargs="+", default=["default", "eva", "3dgs+body"], help="'default': the preset's"
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    import eva_engine
    from eva_engine.data import load_dataset
    from eva_engine.train import preset, train_avatar, with_method

    ds = load_dataset(args.dataset)
    out: dict = {"engine": eva_engine.__file__, "iterations": args.iterations, "methods": {}}
    for method in args.methods:
        config = preset("fast", seed=0)
        config = config if method == "default" else with_method(config, method)
        result = train_avatar(ds, dataclasses.replace(config, iterations=args.iterations))
        out["methods"][method] = {
            "gaussians": len(result.avatar.gaussians),
            "sha256": fingerprint(result.avatar.state_dict()),
        }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
