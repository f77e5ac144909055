"""Where the test suite's CPU time goes: a py-spy raw profile of the whole suite (every process
it starts) summed by process kind and by what runs in it.

    py-spy record --subprocesses -r 25 -f raw -o suite.raw -- \
        .venv/bin/pytest -q -n 2 --dist loadfile -p no:cacheprovider      # OMP_NUM_THREADS=1
    python bench/results/test_suite_runs/spy_summary.py suite.raw --rate 25 --top 25

Samples whose innermost frame waits (select, poll, sleep, locks) are left out. "import" is any
sample under a module import; otherwise the label is the two innermost frames in the project's
own code (eva_engine, jobs, service, tests, bench), "other" when there is none.
"""

from __future__ import annotations

import argparse
import collections
import re

WAITING = ("select", "poll", "wait", "sleep", "epoll", "accept", "recv", "acquire", "futex")
OURS = re.compile(r"\((?:eva_engine|jobs|service|tests|bench)/")


def process_kind(frame: str) -> str:
    """'jobs run', 'eva serve', 'pytest', ... from a py-spy process frame."""
    m = re.search(r'"[^ ]*python3\.11 (?:-m )?(\S+)(?: (\S+))?', frame)
    if not m:
        return "other"
    kind = (m.group(1).split("/")[-1] + " " + (m.group(2) or "")).strip().rstrip('"')
    if "pytest" in kind or kind.startswith("-u -c"):
        return "pytest (its workers)"
    return kind


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("raw")
    ap.add_argument("--rate", type=float, default=25.0, help="py-spy's samples per second")
    ap.add_argument("--top", type=int, default=25)
    args = ap.parse_args()
    kinds: collections.Counter = collections.Counter()
    labels: collections.Counter = collections.Counter()
    for line in open(args.raw):
        stack, _, count = line.rstrip().rpartition(" ")
        if not count.isdigit():
            continue
        frames = stack.split(";")
        if any(w in frames[-1] for w in WAITING):
            continue
        processes = [f for f in frames if f.startswith("process ")]
        kind = process_kind(processes[-1]) if processes else "other"
        kinds[kind] += int(count)
        ours = [f.split(" (")[0] for f in frames if OURS.search(f)]
        label = "import" if "_find_and_load" in stack else (" > ".join(ours[-2:]) if ours else "other")
        labels[(kind, label)] += int(count)
    seconds = sum(kinds.values()) / args.rate
    print(f"CPU seconds sampled (not waiting): {seconds:.1f}\n")
    print("| process | CPU s |\n|---|---:|")
    for kind, n in kinds.most_common():
        print(f"| {kind} | {n / args.rate:.1f} |")
    print("\n| process | what runs (innermost project frames) | CPU s |\n|---|---|---:|")
    for (kind, label), n in labels.most_common(args.top):
        print(f"| {kind} | {label} | {n / args.rate:.1f} |")


if __name__ == "__main__":
    main()
