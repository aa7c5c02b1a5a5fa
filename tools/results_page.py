"""Regenerate the results page and the README's results table from ``results/*.json``.

Every current figure of the project lives in one JSON file per table under ``results/``,
with the commands that produced it, the machine, the commit and the protocol. This
script renders them::

    python tools/results_page.py            # writes docs/results.md and README.md's table
    python tools/results_page.py --check    # exit 1 when either differs from the files

A table file has ``title``, ``order`` (its place on the page), ``summary`` (what the
figures mean, one paragraph), ``protocol``, ``runs`` (``id``, ``commit``, ``machine``,
``command``: a list of shell lines) and optional ``notes`` and ``image`` (a path
relative to ``docs/``), and one of two kinds (a run's ``commit`` may be empty when the
table names the commit of each row):

- ``"kind": "seeds"``: per-seed training cells (``cells``: ``run``, ``scene``,
  ``method``, ``seed``, ``psnr``, ``masked_psnr``, ``recall``, ``n_gaussians``,
  ``train_seconds``) of the ``methods`` (``id``, ``label``, and ``run`` when a method's
  row comes from another run than the first) on the ``scenes`` (``id``, ``label``),
  summarised here: mean ± the population std over seeds, recall per seed, and
  Gaussians and training time as ratios to the ``baseline`` method's cell of the same
  run, scene and seed;
- ``"kind": "table"``: ``columns`` (``key``, ``title``, optional ``format``, a Python
  format spec for numbers, and ``suffix``) and ``rows`` (objects keyed by column).

The README carries one table between ``<!-- results-table: NAME -->`` and
``<!-- end results-table -->``, where NAME is the file's stem.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
PAGE = Path("docs/results.md")
README = Path("README.md")
RESULTS = Path("results")
COMMON_KEYS = ("title", "order", "kind", "summary", "protocol", "runs")
RUN_KEYS = ("id", "commit", "machine", "command")
CELL_KEYS = ("run", "scene", "method", "seed", "psnr", "masked_psnr", "recall", "n_gaussians", "train_seconds")
MARKER = re.compile(r"<!-- results-table: (?P<name>[\w-]+) -->\n.*?<!-- end results-table -->", re.S)


class ResultsError(ValueError):
    """A results file or the README is not as this script expects; the message names it."""


def load_tables(folder: Path) -> dict[str, dict[str, Any]]:
    """Every ``*.json`` table of ``folder`` by file stem, in page order, validated."""
    tables = {}
    for path in sorted(folder.glob("*.json")):
        try:
            table = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ResultsError(f"{path}: not JSON ({e})") from None
        validate(table, path)
        tables[path.stem] = table
    if not tables:
        raise ResultsError(f"{folder}: no *.json results files")
    return dict(sorted(tables.items(), key=lambda item: (item[1]["order"], item[0])))


def validate(table: Any, path: Path) -> None:
    """Raise ResultsError naming ``path`` and the first thing missing or wrong."""
    if not isinstance(table, dict):
        raise ResultsError(f"{path}: expected a JSON object")
    for key in COMMON_KEYS:
        if key not in table:
            raise ResultsError(f"{path}: missing '{key}'")
    if not table["runs"]:
        raise ResultsError(f"{path}: 'runs' is empty")
    for i, run in enumerate(table["runs"]):
        for key in RUN_KEYS:
            if key not in run:
                raise ResultsError(f"{path}: run {i}: missing '{key}'")
    if table["kind"] == "seeds":
        for key in ("baseline", "methods", "scenes", "cells"):
            if key not in table:
                raise ResultsError(f"{path}: missing '{key}'")
        run_ids = {run["id"] for run in table["runs"]}
        for i, cell in enumerate(table["cells"]):
            for key in CELL_KEYS:
                if key not in cell:
                    raise ResultsError(f"{path}: cell {i}: missing '{key}'")
            if cell["run"] not in run_ids:
                raise ResultsError(f"{path}: cell {i}: run '{cell['run']}' is not one of 'runs'")
    elif table["kind"] == "table":
        for key in ("columns", "rows"):
            if key not in table:
                raise ResultsError(f"{path}: missing '{key}'")
        keys = {column["key"] for column in table["columns"]}
        for i, row in enumerate(table["rows"]):
            unknown = set(row) - keys
            if unknown:
                raise ResultsError(f"{path}: row {i}: no column for {sorted(unknown)}")
    else:
        raise ResultsError(f"{path}: 'kind' must be 'seeds' or 'table', got {table['kind']!r}")


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def span(values: list[float], fmt: str, suffix: str = "") -> str:
    """'a–b' of the smallest and largest value, or one value when they print alike."""
    low, high = format(min(values), fmt), format(max(values), fmt)
    return f"{low}{suffix}" if low == high else f"{low}–{high}{suffix}"


def seed_range(seeds: list[int]) -> str:
    if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 2:
        return f"seeds {seeds[0]}–{seeds[-1]}"
    return "seeds " + ", ".join(str(s) for s in seeds)


def render_seeds(table: dict[str, Any]) -> str:
    """Per (scene, method): mean ± std, recall per seed, ratios to the baseline."""
    cells = table["cells"]
    baseline = table["baseline"]
    by_key = {(c["run"], c["scene"], c["method"], c["seed"]): c for c in cells}
    scenes = table["scenes"]
    has = {key: any(c[key] is not None for c in cells) for key in ("masked_psnr", "recall")}
    seeds_all = sorted({c["seed"] for c in cells})
    header = (["scene"] if len(scenes) > 1 else []) + ["method", "PSNR (dB)"]
    header += ["masked PSNR (dB)"] if has["masked_psnr"] else []
    header += [f"recall, {seed_range(seeds_all)} (mean)"] if has["recall"] else []
    base_label = label_of(table["methods"], baseline)
    header += [f"Gaussians (× {base_label})", f"training time (× {base_label})"]
    rows = []
    for scene in scenes:
        for method in table["methods"]:
            run = method.get("run", table["runs"][0]["id"])
            mine = sorted((c for c in cells
                           if c["run"] == run and c["scene"] == scene["id"] and c["method"] == method["id"]),
                          key=lambda c: c["seed"])
            if not mine:
                continue
            base = []
            for c in mine:
                b = by_key.get((c["run"], c["scene"], baseline, c["seed"]))
                if b is None:
                    raise ResultsError(f"{table['title']}: no {baseline} cell for run {c['run']}, "
                                       f"scene {c['scene']}, seed {c['seed']}")
                base.append(b)
            psnr = [c["psnr"] for c in mine]
            row = ([scene["label"]] if len(scenes) > 1 else []) + [method["label"], mean_std(psnr)]
            if has["masked_psnr"]:
                masked = [c["masked_psnr"] for c in mine if c["masked_psnr"] is not None]
                row.append(mean_std(masked) if masked else "–")
            if has["recall"]:
                recall = [c["recall"] for c in mine if c["recall"] is not None]
                row.append(" / ".join(f"{r:.2f}" for r in recall) + f" ({statistics.fmean(recall):.3f})"
                           if recall else "–")
            if method["id"] == baseline:
                row.append(f"{statistics.fmean(c['n_gaussians'] for c in mine) / 1000:.1f}k")
                row.append(span([c["train_seconds"] for c in mine], ".0f", " s"))
            else:
                count = [c["n_gaussians"] / b["n_gaussians"] for c, b in zip(mine, base)]
                time = [c["train_seconds"] / b["train_seconds"] for c, b in zip(mine, base)]
                row.append(span(count, ".2f", "×"))
                spread = "" if len(time) == 1 else f" ({span(time, '.2f')})"
                row.append(f"{statistics.median(time):.2f}×{spread}")
            rows.append(row)
    return markdown_table(header, rows)


def label_of(methods: list[dict[str, str]], method_id: str) -> str:
    return next((m["label"] for m in methods if m["id"] == method_id), method_id)


def mean_std(values: list[float]) -> str:
    return f"{statistics.fmean(values):.2f} ± {statistics.pstdev(values):.2f}"


def cell_text(value: Any, column: dict[str, str]) -> str:
    if value is None:
        return "–"
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return format(value, column.get("format", "")) + column.get("suffix", "")
    return str(value)


def render_plain(table: dict[str, Any]) -> str:
    columns = table["columns"]
    rows = [[cell_text(row.get(c["key"]), c) for c in columns] for row in table["rows"]]
    return markdown_table([c["title"] for c in columns], rows)


def render_table(table: dict[str, Any]) -> str:
    """The table's markdown rows, computed from the file."""
    return render_seeds(table) if table["kind"] == "seeds" else render_plain(table)


def render_section(name: str, table: dict[str, Any], protocols: dict[str, str]) -> str:
    """One table's section; ``protocols`` maps a protocol already written to its title."""
    parts = [f"## {table['title']}", table["summary"]]
    if table.get("image"):
        parts.append(f"![{table['title']}]({table['image']})")
    parts.append(render_table(table))
    if table.get("notes"):
        parts.append("\n".join(f"- {note}" for note in table["notes"]))
    first = protocols.setdefault(table["protocol"], table["title"])
    if first == table["title"]:
        parts.append(f"**Protocol.** {table['protocol']}")
    else:
        parts.append(f"**Protocol.** As for [{first}](#{anchor(first)}).")
    for run in table["runs"]:
        label = "" if len(table["runs"]) == 1 else f" `{run['id']}`"
        commit = f"commit `{run['commit']}`, " if run["commit"] else ""
        commands = "\n".join(run["command"])
        parts.append(f"**Run{label}:** {commit}{run['machine']}.\n\n```bash\n{commands}\n```")
    parts.append(f"Source: [results/{name}.json](../results/{name}.json).")
    return "\n\n".join(parts)


def render_page(tables: dict[str, dict[str, Any]]) -> str:
    head = ("# Results\n\n"
            "The current figures of the project, one section per file of [results/](../results/), "
            "each with its protocol, the commit and machine that produced it and the commands. "
            "This page is generated: edit the JSON files and run `python tools/results_page.py` "
            "(`--check` tells whether this page and the README's table are up to date). "
            "What was tried and not kept is in [decisions.md](decisions.md); older figures are "
            "in git history (see the [changelog](../CHANGELOG.md)).\n\n"
            "Contents:\n\n" + "\n".join(f"- [{t['title']}](#{anchor(t['title'])})" for t in tables.values()))
    protocols: dict[str, str] = {}
    return head + "\n\n" + "\n\n".join(render_section(name, t, protocols) for name, t in tables.items()) + "\n"


def anchor(title: str) -> str:
    """GitHub's heading anchor: lower case, punctuation out, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", title.lower())
    return text.replace(" ", "-")


def readme_with_tables(readme: str, tables: dict[str, dict[str, Any]]) -> str:
    """``readme`` with each marked block replaced by the named table, rendered afresh."""
    if not MARKER.search(readme):
        raise ResultsError(f"{README}: no '<!-- results-table: NAME -->' ... '<!-- end results-table -->' block")

    def block(match: re.Match) -> str:
        name = match["name"]
        if name not in tables:
            raise ResultsError(f"{README}: results-table '{name}' has no results/{name}.json")
        return (f"<!-- results-table: {name} -->\n{render_table(tables[name])}\n\n"
                f"*Generated from [results/{name}.json](results/{name}.json); the protocol, the commands "
                f"and every other table: [docs/results.md](docs/results.md).*\n<!-- end results-table -->")

    return MARKER.sub(block, readme)


def expected_files(repo: Path) -> dict[Path, str]:
    """The page and the README as the results files give them."""
    tables = load_tables(repo / RESULTS)
    return {PAGE: render_page(tables), README: readme_with_tables((repo / README).read_text(), tables)}


def stale_files(repo: Path) -> list[Path]:
    """The files (relative to ``repo``) whose text differs from what the results give."""
    return [rel for rel, text in expected_files(repo).items()
            if not (repo / rel).is_file() or (repo / rel).read_text() != text]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 when a file is out of date")
    ap.add_argument("--repo", type=Path, default=REPO, help="repository root (default: this checkout)")
    args = ap.parse_args(argv)
    try:
        if args.check:
            stale = stale_files(args.repo)
            for rel in stale:
                print(f"{rel} is out of date: run python tools/results_page.py", file=sys.stderr)
            return 1 if stale else 0
        for rel, text in expected_files(args.repo).items():
            (args.repo / rel).write_text(text)
            print(f"wrote {rel}")
        return 0
    except ResultsError as e:
        print(f"results_page: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
