"""``bench/results/README.md``: what each result in ``bench/results/`` is, and which docs quote it.

    python -m bench index            # rewrite the index
    python -m bench index --check    # exit 1 if the committed index is stale (a test runs this)

An entry is a top-level folder, or the top-level files that share a stem (``align.json``,
``align.md``; a sheet ``real_videos_before_hybrik_taiji.jpg`` joins ``real_videos_before``). What
it is: the first heading of its Markdown (a folder's ``README.md``, else its first ``.md``). Quoted
by: the docs (``README.md``, ``docs/*.md``) that name one of its files, its stem (if it has a
``_``) or the folder, brace groups spelled out; else "input of" the quoted entries whose Markdown
names it the same way (per-seed runs merged into a table). An entry neither quoted nor an input
is superseded: ``--check`` fails until it is removed (git history keeps it).
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
INDEX = RESULTS / "README.md"
DOCS = ("README.md", "docs/*.md")


def heading(md: Path) -> str:
    """The first Markdown heading of ``md`` (without the #s), or ''."""
    for line in md.read_text(errors="replace").splitlines():
        if line.startswith("#"):
            return line.lstrip("#").strip()
    return ""


def entries(results: Path) -> dict[str, list[Path]]:
    """Entry name -> its paths: each folder, and files grouped by stem; a file whose stem extends
    another entry's with ``_<suffix>`` (contact sheets, logs) joins the longest such entry."""
    groups: dict[str, list[Path]] = {}
    files = sorted(p for p in results.iterdir() if p.name != INDEX.name and not p.name.startswith("."))
    for p in files:
        if p.is_dir():
            groups[p.name + "/"] = [p]
    stems = {p.name.split(".", 1)[0] for p in files if p.is_file() and p.suffix in (".md", ".json")}
    for p in files:
        if not p.is_file():
            continue
        stem = p.name.split(".", 1)[0]
        owner = stem if stem in stems else None
        if owner is None:
            prefixes = [s for s in stems if stem.startswith(s + "_")]
            owner = max(prefixes, key=len) if prefixes else stem
        groups.setdefault(owner, []).append(p)
    return dict(sorted(groups.items()))


def what_it_is(paths: list[Path]) -> str:
    first = paths[0]
    if first.is_dir():
        mds = [first / "README.md"] if (first / "README.md").is_file() else sorted(first.glob("*.md"))
        return heading(mds[0]) if mds else ""
    mds = [p for p in paths if p.suffix == ".md"]
    return heading(mds[0]) if mds else ""


BRACES = re.compile(r"[\w./-]*\{[^{}\s`]*\}[\w./{},-]*")


def expand_braces(text: str) -> str:
    """``text`` with every shell-style brace group spelled out, appended: the docs name per-seed
    files as ``real_videos_expr_seed{0,1,2}`` or ``blink_sweep_{product,eva}.md``."""

    def expand(word: str) -> list[str]:
        m = re.search(r"\{([^{}]*)\}", word)
        if m is None:
            return [word]
        head, tail = word[: m.start()], word[m.end() :]
        return [w for alt in m.group(1).split(",") for w in expand(head + alt + tail)]

    words = [w for token in BRACES.findall(text) for w in expand(token)]
    return text + "\n" + "\n".join(words)


def quoted_by(name: str, paths: list[Path], docs: dict[str, str]) -> list[str]:
    """The docs whose text names one of ``paths`` (by file name) or the folder ``name``."""
    if name.endswith("/"):
        pattern = re.compile(rf"(?<![\w-]){re.escape(name)}")
    else:
        # By file name, or by the bare stem where it cannot be a word of prose (``_`` in it).
        names = "|".join(re.escape(p.name) for p in paths) + (f"|{re.escape(name)}" if "_" in name else "")
        pattern = re.compile(rf"(?<![\w-])(?:{names})(?![\w-])")
    return [doc for doc, text in docs.items() if pattern.search(text)]


def build_index(root: Path = ROOT) -> tuple[str, list[str]]:
    """(the index's Markdown, the entries nothing quotes)."""
    results = root / "bench" / "results"
    docs = {
        str(p.relative_to(root)): expand_braces(p.read_text(errors="replace"))
        for pattern in DOCS
        for p in sorted(root.glob(pattern))
    }
    groups = entries(results)
    quoted = {name: quoted_by(name, paths, docs) for name, paths in groups.items()}
    # A result no doc names may be an input of one that is (per-seed runs merged into a table):
    # the quoted result's Markdown names it in its command or text.
    sources = {
        name: expand_braces("\n".join(md.read_text(errors="replace") for md in markdown_files(paths)))
        for name, paths in groups.items()
        if quoted[name]
    }
    rows, inputs, superseded = [], 0, []
    for name, paths in groups.items():
        files = "folder" if name.endswith("/") else ", ".join(sorted(p.suffix.lstrip(".") for p in paths))
        where = ", ".join(quoted[name])
        if not where:
            parents = [p for p in quoted_by(name, paths, sources) if p != name]
            where = "input of " + ", ".join(f"`{p}`" for p in parents) if parents else ""
            inputs += bool(parents)
            if not parents:
                superseded.append(name)
        what = what_it_is(paths).replace("|", "\\|") or "–"
        rows.append(f"| `{name}` | {files} | {what} | {where or '–'} |")
    text = "\n".join(
        [
            "# bench/results: what each result is",
            "",
            "Generated by `python -m bench index` (a test checks it is current): each folder,",
            "and the files that share a stem, with the first heading of its Markdown and the docs that",
            f"quote it. {len(groups)} entries: {len(groups) - inputs - len(superseded)} quoted by the docs,",
            f"{inputs} inputs of a quoted result (per-seed runs merged into its table), {len(superseded)}",
            "quoted by nothing. A superseded result is removed: git history keeps it.",
            "",
            "| entry | files | what it is | quoted by |",
            "|---|---|---|---|",
            *rows,
            "",
        ]
    )
    return text, superseded


def markdown_files(paths: list[Path]) -> list[Path]:
    """The Markdown of an entry: its files', or every ``.md`` under its folder."""
    mds = []
    for p in paths:
        mds += sorted(p.rglob("*.md")) if p.is_dir() else ([p] if p.suffix == ".md" else [])
    return mds


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if the committed index is stale")
    args = ap.parse_args(argv)
    text, superseded = build_index()
    if args.check:
        if not INDEX.is_file() or INDEX.read_text() != text:
            sys.exit(f"{INDEX.relative_to(ROOT)} is stale: python -m bench index")
        if superseded:
            sys.exit(f"quoted by no doc and no quoted result (remove them): {', '.join(superseded)}")
        return
    INDEX.write_text(text)
    print(f"wrote {INDEX.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
