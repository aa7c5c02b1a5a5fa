"""``promptgs report RESULTS.jsonl --out DIR``: charts and tables from benchmark results.

Reads the JSON-lines file that ``promptgs bench`` writes (schema ``promptgs-bench/1``,
docs/interfaces.md) and writes into DIR:

- ``psnr_vs_time.png``, ``masked_psnr_vs_time.png``: quality against wall time per scene,
  mean ± std over seeds, with the Pareto front (higher quality, less time);
- ``psnr_vs_gaussians.png``: PSNR against the Gaussian count; budget sweeps of a method
  joined as a curve;
- ``compaction.png``: PSNR (and masked PSNR where the scene has masks) against the Gaussian
  count, each method joined to the same method with ``+compact`` (written when the
  results hold compacted cells);
- ``recall.png``: tiny-object recall per method, per scene that has it;
- ``table.md``: per-scene tables in the layout of the paper's Table II, a "Gaussian
  economy" table per budget sweep, and the failed cells with their messages;
- ``crops_<scene>.png`` (and ``crops.png``, the first): ground truth and each method's
  test render cropped around tiny objects, upscaled with nearest neighbour;
- ``summary.json``: the aggregate rows, the failed cells, the files written and notes.

Failed cells (``"status": "error"``) appear in the table only, never in the charts.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import PromptGSError
from .process import is_finite

SCHEMA = "promptgs-bench/1"
REQUIRED_KEYS = ("cell", "scene", "method", "iterations", "seed", "status")
STAT_KEYS = (
    "psnr", "ssim", "masked_psnr", "object_region_psnr", "recall", "n_gaussians",
    "wall_seconds", "train_seconds", "seconds_per_step", "peak_rss_mb",
)

# Fixed method order, display names and styles, the same in every chart and table:
# baselines grey / green, PromptGS variants in warm colours.
METHOD_ORDER = ("3dgs", "absgs", "promptgs-center", "promptgs-1", "promptgs-2", "promptgs-auto", "promptgs-propose")
METHOD_NAMES = {
    "3dgs": "3DGS",
    "absgs": "AbsGS",
    "promptgs-center": "PromptGS, centre box",
    "promptgs-1": "PromptGS, 1 box",
    "promptgs-2": "PromptGS, a box per group",
    "promptgs-auto": "PromptGS, auto prompts",
    "promptgs-propose": "PromptGS, proposed prompts",
}
METHOD_STYLES = {  # method -> (colour, marker)
    "3dgs": ("#7f7f7f", "o"),
    "absgs": ("#2ca02c", "s"),
    "promptgs-center": ("#f2b705", "^"),
    "promptgs-1": ("#f07c19", "D"),
    "promptgs-2": ("#d62728", "v"),
    "promptgs-auto": ("#8c2d04", "P"),
    "promptgs-propose": ("#9467bd", "*"),
}
_OTHER_STYLES = [("#1f77b4", "X"), ("#17becf", "h"), ("#e377c2", "p"), ("#bcbd22", "d")]

# Crop sheet layout (pixels): a label strip on the left, a title strip on top, and a gap
# before every crop. Crop (row i, column j) starts at
# x = CROP_LABEL_W + CROP_GAP + j * (window * scale + CROP_GAP), y likewise with CROP_HEADER_H.
CROP_LABEL_W = 96
CROP_HEADER_H = 18
CROP_GAP = 4

LPIPS_NOTE = "LPIPS is not computed, so the paper's LPIPS↓ column is left out."


# ---------------------------------------------------------------------------- reading


def load_results(path: Path) -> list[dict]:
    """Read a ``promptgs-bench/1`` JSON-lines results file; one dict per non-blank line.

    Raises PromptGSError (one line, naming the file and the line number) for a missing or
    unreadable file, a line that is not a JSON object, a wrong schema, a missing key or
    an unknown status.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise PromptGSError(f"{path}: results file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise PromptGSError(f"{path}: cannot read results file ({exc})") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        where = f"{path}, line {lineno}"
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            raise PromptGSError(f"{where}: not valid JSON ({exc.msg})") from None
        if not isinstance(row, dict):
            raise PromptGSError(f"{where}: expected a JSON object, got {type(row).__name__}")
        if row.get("schema") != SCHEMA:
            raise PromptGSError(f"{where}: schema {row.get('schema')!r}, expected {SCHEMA!r}")
        missing = [k for k in REQUIRED_KEYS if k not in row]
        if missing:
            raise PromptGSError(f"{where}: missing key(s) {', '.join(missing)}")
        if row["status"] not in ("ok", "error"):
            raise PromptGSError(f"{where}: status {row['status']!r}, expected 'ok' or 'error'")
        rows.append(row)
    return rows


def current_rows(rows: Iterable[dict]) -> list[dict]:
    """One row per cell id: its last ok row, or its last error row when it never succeeded.

    A grid re-run appends a new line for a cell that failed before, so earlier failures of
    a cell that later succeeded are dropped. File order is kept.
    """
    last: dict[str, dict] = {}
    for row in rows:
        prev = last.get(row["cell"])
        if prev is None or row["status"] == "ok" or prev["status"] == "error":
            last[row["cell"]] = row
    return list(last.values())


# ---------------------------------------------------------------------------- aggregation


COMPACT_SUFFIX = "+compact"


def _method_rank(method: str) -> tuple[int, int, str]:
    """Known methods in METHOD_ORDER, each followed by its ``+compact`` variant."""
    base = method.removesuffix(COMPACT_SUFFIX)
    compact = int(method.endswith(COMPACT_SUFFIX))
    if base in METHOD_ORDER:
        return (METHOD_ORDER.index(base), compact, "")
    return (len(METHOD_ORDER), compact, method)


def _budget_rank(budget: Any) -> tuple[int, float]:
    if budget is None:
        return (0, 0.0)
    if isinstance(budget, (int, float)):
        return (1, float(budget))
    return (2, 0.0)


def _cell_sort_key(scene_order: dict[str, int], scene: str, method: str, budget: Any, iterations: int) -> tuple:
    return (scene_order[scene], _method_rank(method), _budget_rank(budget), iterations)


def _finite(values: Iterable[Any]) -> list[float]:
    return [float(v) for v in values if is_finite(v)]


def aggregate(rows: Iterable[dict]) -> list[dict]:
    """Mean and population std over seeds of each ok cell group (scene, method, budget, iterations).

    Each returned dict has ``scene``, ``method``, ``budget``, ``iterations``, ``dataset``,
    ``images``, ``n_seeds``, ``seeds`` (sorted) and, for every key in STAT_KEYS,
    ``<key>_mean``, ``<key>_std`` and ``<key>_n`` (the number of seeds with a finite
    value: seeds whose value is None are left out of that key's statistics; mean and std
    are None when no seed has one). Error rows are ignored. Groups
    are sorted by scene (first appearance), method (METHOD_ORDER), budget, iterations.
    """
    ok = [r for r in current_rows(rows) if r["status"] == "ok"]
    scene_order = {s: i for i, s in enumerate(dict.fromkeys(r["scene"] for r in ok))}
    groups: dict[tuple, list[dict]] = {}
    for r in ok:
        groups.setdefault((r["scene"], r["method"], r.get("budget"), int(r["iterations"])), []).append(r)
    out = []
    for key in sorted(groups, key=lambda k: _cell_sort_key(scene_order, *k)):
        members = sorted(groups[key], key=lambda r: r["seed"])
        agg: dict[str, Any] = {
            "scene": key[0], "method": key[1], "budget": key[2], "iterations": key[3],
            "dataset": members[0].get("dataset"), "images": members[0].get("images") or "images",
            "n_seeds": len(members), "seeds": [r["seed"] for r in members],
        }
        for k in STAT_KEYS:
            vals = _finite(r.get(k) for r in members)
            agg[f"{k}_mean"] = float(np.mean(vals)) if vals else None
            agg[f"{k}_std"] = float(np.std(vals)) if vals else None
            agg[f"{k}_n"] = len(vals)
        out.append(agg)
    return out


def pareto_front(points: list[tuple[float | None, float | None]]) -> list[int]:
    """Indices of the points no other point beats: (time, quality), less time and more quality is better.

    A point is on the front when no other point has time <= and quality >= with at least
    one strict. Points with a None or non-finite coordinate are ignored. The indices are
    sorted by time (then by quality), so the front reads left to right.
    """
    valid = [
        (i, float(t), float(q)) for i, (t, q) in enumerate(points)
        if t is not None and q is not None and math.isfinite(t) and math.isfinite(q)
    ]
    front = [
        (t, q, i) for i, t, q in valid
        if not any(t2 <= t and q2 >= q and (t2 < t or q2 > q) for _, t2, q2 in valid)
    ]
    return [i for _, _, i in sorted(front)]


# ---------------------------------------------------------------------------- labels and formats


def method_name(method: str) -> str:
    base = method.removesuffix(COMPACT_SUFFIX)
    name = METHOD_NAMES.get(base, base)
    return name + ", compacted" if method.endswith(COMPACT_SUFFIX) else name


def method_styles(methods: Iterable[str]) -> dict[str, tuple[str, str]]:
    """(colour, marker) per method: fixed for the known methods (a ``+compact`` variant
    shares its method's; charts draw it hollow), then cool colours in order."""
    styles, extra = {}, 0
    for m in sorted(set(methods), key=_method_rank):
        base = m.removesuffix(COMPACT_SUFFIX)
        if base in METHOD_STYLES:
            styles[m] = METHOD_STYLES[base]
        else:
            styles[m] = _OTHER_STYLES[extra % len(_OTHER_STYLES)]
            extra += 1
    return styles


def _budget_text(budget: Any) -> str:
    if budget is None:
        return "no budget"
    return f"{budget:,}" if isinstance(budget, int) else str(budget)


def cell_label(agg: dict, show_iterations: bool, short: bool = False) -> str:
    """The row label: the method, plus the budget when one is set and the iterations when asked."""
    parts = [agg["method"] if short else method_name(agg["method"])]
    if agg["budget"] is not None:
        parts.append(f"b{_budget_text(agg['budget'])}" if short else f"budget {_budget_text(agg['budget'])}")
    if show_iterations:
        parts.append(f"{agg['iterations']} it")
    return " · ".join(parts) if not short else " ".join(parts)


def _fmt(mean: float | None, std: float | None, n_seeds: int, fmt: str, n_values: int | None = None) -> str:
    """"mean ± std" over the seeds that have the value; "(k of n seeds)" when some lack it."""
    if mean is None:
        return "–"
    n = n_seeds if n_values is None else n_values
    text = format(mean, fmt)
    if n > 1 and std is not None:
        text += " ± " + format(std, fmt)
    if n < n_seeds:
        text += f" ({n} of {n_seeds} seeds)"
    return text


def _stat(agg: dict, key: str, fmt: str) -> str:
    return _fmt(agg[f"{key}_mean"], agg[f"{key}_std"], agg["n_seeds"], fmt, agg.get(f"{key}_n"))


def _by_scene(aggs: list[dict]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for a in aggs:
        out.setdefault(a["scene"], []).append(a)
    return out


def _scenes_where(aggs: list[dict], keep: Any) -> dict[str, list[dict]]:
    """Per scene, the cells for which ``keep(cell)`` holds; scenes left empty are dropped."""
    scenes = {s: [a for a in cells if keep(a)] for s, cells in _by_scene(aggs).items()}
    return {s: c for s, c in scenes.items() if c}


# ---------------------------------------------------------------------------- table


def _baseline(cells: list[dict], iterations: int) -> dict | None:
    for a in cells:
        if a["method"] == "3dgs" and a["budget"] is None and a["iterations"] == iterations:
            return a
    return None


def table_markdown(aggs: list[dict], failed: list[dict], loads: dict[str, list[float]] | None = None) -> str:
    """The Markdown of table.md: per scene a Table II-style table, the Gaussian economy, failures."""
    scenes = list(dict.fromkeys([a["scene"] for a in aggs] + [r["scene"] for r in failed]))
    lines = ["# Benchmark results", ""]
    for scene in scenes:
        cells = [a for a in aggs if a["scene"] == scene]
        scene_failed = [r for r in failed if r["scene"] == scene]
        iters = sorted({a["iterations"] for a in cells} | {int(r["iterations"]) for r in scene_failed})
        show_it = len(iters) > 1
        lines += [f"## {scene}", ""]
        dataset = (cells or scene_failed)[0].get("dataset")
        info = [f"dataset `{dataset}`"] if dataset else []
        info.append(f"{', '.join(map(str, iters))} iterations")
        if loads and loads.get(scene):
            lo, hi = min(loads[scene]), max(loads[scene])
            info.append(f"1-min load average at cell start {lo:.1f}–{hi:.1f}")
        lines += ["; ".join(info) + ". Values are mean ± population std over the seeds.", ""]
        lines += [
            "| Method | PSNR↑ | SSIM↑ | masked PSNR↑ | recall↑ | Gaussians | wall time (s) | time vs 3DGS | peak memory (MB) | seeds |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        # one row per group, ok or all-failed, in the usual order
        fail_groups: dict[tuple, list[dict]] = {}
        for r in scene_failed:
            fail_groups.setdefault((r["method"], r.get("budget"), int(r["iterations"])), []).append(r)
        keys = {(a["method"], a["budget"], a["iterations"]): a for a in cells}
        all_keys = sorted(set(keys) | set(fail_groups), key=lambda k: (_method_rank(k[0]), _budget_rank(k[1]), k[2]))
        for key in all_keys:
            a = keys.get(key)
            n_fail = len(fail_groups.get(key, []))
            if a is None:
                label = cell_label({"method": key[0], "budget": key[1], "iterations": key[2]}, show_it)
                lines.append(f"| {label} | failed | | | | | | | | 0 ({n_fail} failed) |")
                continue
            base = _baseline(cells, a["iterations"])
            ratio = (
                f"{a['wall_seconds_mean'] / base['wall_seconds_mean']:.2f}×"
                if base and a["wall_seconds_mean"] is not None and base["wall_seconds_mean"]
                else "–"
            )
            seeds = f"{a['n_seeds']}" + (f" ({n_fail} failed)" if n_fail else "")
            lines.append(
                f"| {cell_label(a, show_it)} "
                f"| {_stat(a, 'psnr', '.2f')} "
                f"| {_stat(a, 'ssim', '.3f')} "
                f"| {_stat(a, 'masked_psnr', '.2f')} "
                f"| {_stat(a, 'recall', '.2f')} "
                f"| {_stat(a, 'n_gaussians', ',.0f')} "
                f"| {_stat(a, 'wall_seconds', '.1f')} "
                f"| {ratio} "
                f"| {_stat(a, 'peak_rss_mb', ',.0f')} "
                f"| {seeds} |"
            )
        lines += [
            "",
            LPIPS_NOTE + " masked PSNR: over object pixels; recall: fraction of (object, view) pairs "
            "reconstructed; wall time: the cell's process, load + train + eval; time vs 3DGS: wall time "
            "over 3DGS's (no budget, same iterations).",
            "",
        ]
        lines += _economy_lines(cells)
        lines += _compaction_lines(cells)
    if failed:
        lines += ["## Failed cells", ""]
        lines += [f"- `{r['cell']}`: {r.get('error') or 'no message'}" for r in failed]
        lines.append("")
    return "\n".join(lines)


def _economy_lines(cells: list[dict]) -> list[str]:
    """Per method (and iteration count) with more than one budget: what the budget costs in PSNR."""
    sweeps: dict[tuple[str, int], list[dict]] = {}
    for a in cells:
        sweeps.setdefault((a["method"], a["iterations"]), []).append(a)
    sweeps = {k: v for k, v in sweeps.items() if len({repr(a["budget"]) for a in v}) > 1}
    if not sweeps:
        return []
    lines = [
        "### Gaussian economy",
        "",
        "| Method | budget | Gaussians | PSNR↑ | ΔPSNR vs no budget | % of no-budget Gaussians |",
        "|---|---|---|---|---|---|",
    ]
    show_it = len({k[1] for k in sweeps}) > 1
    for (method, iterations), group in sweeps.items():
        full = next((a for a in group if a["budget"] is None), None)
        name = method_name(method) + (f" · {iterations} it" if show_it else "")
        for a in sorted(group, key=lambda a: _budget_rank(a["budget"])):
            delta = pct = "–"
            if full is not None and a["psnr_mean"] is not None and full["psnr_mean"] is not None:
                delta = f"{a['psnr_mean'] - full['psnr_mean']:+.2f}"
            if full is not None and a["n_gaussians_mean"] is not None and full["n_gaussians_mean"]:
                pct = f"{100.0 * a['n_gaussians_mean'] / full['n_gaussians_mean']:.0f}%"
            lines.append(
                f"| {name} | {_budget_text(a['budget'])} "
                f"| {_stat(a, 'n_gaussians', ',.0f')} "
                f"| {_stat(a, 'psnr', '.2f')} | {delta} | {pct} |"
            )
    return lines + [""]


def compaction_pairs(cells: list[dict]) -> list[tuple[dict, dict]]:
    """(cell, the same cell compacted) for every method run both ways (same budget and iterations)."""
    by_key = {(a["method"], repr(a["budget"]), a["iterations"]): a for a in cells}
    pairs = []
    for (method, budget, iterations), a in by_key.items():
        if method.endswith(COMPACT_SUFFIX):
            continue
        c = by_key.get((method + COMPACT_SUFFIX, budget, iterations))
        if c is not None:
            pairs.append((a, c))
    return pairs


def _compaction_lines(cells: list[dict]) -> list[str]:
    """Per method run with and without ``--compact``: what compaction removes and costs."""
    pairs = compaction_pairs(cells)
    if not pairs:
        return []
    show_it = len({a["iterations"] for a, _ in pairs}) > 1
    lines = [
        "### Compaction",
        "",
        "| Method | Gaussians → compacted | share kept | ΔPSNR | Δmasked PSNR | Δrecall | time compacted / not |",
        "|---|---|---|---|---|---|---|",
    ]

    def delta(key: str, fmt: str, a: dict, c: dict) -> str:
        if a[f"{key}_mean"] is None or c[f"{key}_mean"] is None:
            return "–"
        return format(c[f"{key}_mean"] - a[f"{key}_mean"], fmt)

    for a, c in pairs:
        kept = c["n_gaussians_mean"] / a["n_gaussians_mean"] if a["n_gaussians_mean"] else float("nan")
        time = c["wall_seconds_mean"] / a["wall_seconds_mean"] if a["wall_seconds_mean"] and c["wall_seconds_mean"] else float("nan")
        lines.append(
            f"| {cell_label(a, show_it)} | {a['n_gaussians_mean']:,.0f} → {c['n_gaussians_mean']:,.0f} | {kept:.2f}× "
            f"| {delta('psnr', '+.2f', a, c)} | {delta('masked_psnr', '+.2f', a, c)} | {delta('recall', '+.2f', a, c)} | {time:.2f}× |"
        )
    return lines + ["", "Differences are of the means over seeds (compacted − not).", ""]


# ---------------------------------------------------------------------------- charts


def _figure(n_panels: int):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncols = min(n_panels, 3)
    nrows = math.ceil(n_panels / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.6 * ncols, 4.4 * nrows), squeeze=False)
    flat = list(axes.ravel())
    for ax in flat[n_panels:]:
        ax.set_visible(False)
    return plt, fig, flat[:n_panels]


def _save(plt, fig, path: Path, title: str) -> None:
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _legend(ax, styles: dict[str, tuple[str, str]], methods: Iterable[str], extra: list | None = None) -> None:
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], color=styles[m][0], marker=styles[m][1], ls="", label=method_name(m),
               **({"mfc": "white"} if m.endswith(COMPACT_SUFFIX) else {}))
        for m in sorted(set(methods), key=_method_rank)
    ]
    ax.legend(handles=handles + (extra or []), fontsize=7, loc="best")


def _plot_cell(ax, a: dict, x: str, y: str, styles: dict, show_it: bool) -> None:
    """One aggregated cell: a point with std error bars on both axes, and its label."""
    colour, marker = styles[a["method"]]
    hollow = {"mfc": "white"} if a["method"].endswith(COMPACT_SUFFIX) else {}
    ax.errorbar(a[f"{x}_mean"], a[f"{y}_mean"], xerr=a[f"{x}_std"] or 0.0, yerr=a[f"{y}_std"] or 0.0,
                fmt=marker, color=colour, ms=7, capsize=3, lw=1, **hollow)
    ax.annotate(cell_label(a, show_it, short=True), (a[f"{x}_mean"], a[f"{y}_mean"]),
                xytext=(5, 4), textcoords="offset points", fontsize=7)


def plot_quality_vs_time(aggs: list[dict], metric: str, path: Path, ylabel: str, styles: dict) -> bool:
    """One panel per scene with ``<metric>_mean``: metric vs wall time, error bars = std over
    seeds, points labelled, the Pareto front as a dashed step line with its points ringed.
    Returns False (nothing written) when no scene has the metric."""
    scenes = _scenes_where(aggs, lambda a: a[f"{metric}_mean"] is not None and a["wall_seconds_mean"] is not None)
    if not scenes:
        return False
    from matplotlib.lines import Line2D

    plt, fig, axes = _figure(len(scenes))
    for ax, (scene, cells) in zip(axes, scenes.items()):
        show_it = len({a["iterations"] for a in cells}) > 1
        for a in cells:
            _plot_cell(ax, a, "wall_seconds", metric, styles, show_it)
        front = pareto_front([(a["wall_seconds_mean"], a[f"{metric}_mean"]) for a in cells])
        xs = [cells[i]["wall_seconds_mean"] for i in front]
        ys = [cells[i][f"{metric}_mean"] for i in front]
        ax.step(xs, ys, where="post", color="black", ls="--", lw=1, zorder=0)
        ax.scatter(xs, ys, s=220, facecolors="none", edgecolors="black", lw=1, zorder=3)
        ax.set_title(scene)
        ax.set_xlabel("wall time per cell (s)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ring = Line2D([], [], color="black", marker="o", mfc="none", ms=10, ls="--", lw=1, label="Pareto front")
        _legend(ax, styles, [a["method"] for a in cells], [ring])
    _save(plt, fig, path, f"{ylabel} vs wall time (mean ± std over seeds; up-left is better)")
    return True


def plot_psnr_vs_gaussians(aggs: list[dict], path: Path, styles: dict) -> bool:
    """PSNR vs Gaussian count per scene; a method's budgets (same iterations) joined in count order."""
    scenes = _scenes_where(aggs, lambda a: a["psnr_mean"] is not None and a["n_gaussians_mean"])
    if not scenes:
        return False
    plt, fig, axes = _figure(len(scenes))
    for ax, (scene, cells) in zip(axes, scenes.items()):
        show_it = len({a["iterations"] for a in cells}) > 1
        sweeps: dict[tuple[str, int], list[dict]] = {}
        for a in cells:
            sweeps.setdefault((a["method"], a["iterations"]), []).append(a)
        for (method, _), group in sweeps.items():
            colour, marker = styles[method]
            group = sorted(group, key=lambda a: a["n_gaussians_mean"])
            if len(group) > 1:
                ax.plot([a["n_gaussians_mean"] for a in group], [a["psnr_mean"] for a in group], color=colour, lw=1.2)
            for a in group:
                _plot_cell(ax, a, "n_gaussians", "psnr", styles, show_it)
        counts = [a["n_gaussians_mean"] for a in cells]
        if max(counts) / min(counts) > 10:
            ax.set_xscale("log")
        ax.set_title(scene)
        ax.set_xlabel("Gaussians")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        _legend(ax, styles, [a["method"] for a in cells])
    _save(plt, fig, path, "PSNR vs Gaussian count (budgets of one method joined)")
    return True


def plot_compaction(aggs: list[dict], path: Path, styles: dict) -> bool:
    """Per scene, PSNR (and masked PSNR where there are masks) against the Gaussian count,
    each method joined to its compacted run. False (nothing written) without pairs."""
    panels = []
    for scene, cells in _by_scene(aggs).items():
        pairs = compaction_pairs(cells)
        if not pairs:
            continue
        panels.append((scene, "psnr", "PSNR (dB)", pairs))
        if any(a["masked_psnr_mean"] is not None for a, _ in pairs):
            panels.append((scene, "masked_psnr", "masked PSNR (dB)", pairs))
    if not panels:
        return False
    plt, fig, axes = _figure(len(panels))
    for ax, (scene, key, ylabel, pairs) in zip(axes, panels):
        show_it = len({a["iterations"] for a, _ in pairs}) > 1
        for a, c in pairs:
            if a[f"{key}_mean"] is None or c[f"{key}_mean"] is None:
                continue
            colour, _ = styles[a["method"]]
            ax.annotate("", (c["n_gaussians_mean"], c[f"{key}_mean"]), (a["n_gaussians_mean"], a[f"{key}_mean"]),
                        arrowprops={"arrowstyle": "->", "color": colour, "lw": 1.2})
            _plot_cell(ax, a, "n_gaussians", key, styles, show_it)
            _plot_cell(ax, c, "n_gaussians", key, styles, show_it)
        ax.set_title(scene)
        ax.set_xlabel("Gaussians")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        _legend(ax, styles, [m["method"] for pair in pairs for m in pair])
    _save(plt, fig, path, "Compaction: each method (filled) → compacted (hollow), mean ± std over seeds")
    return True


def plot_recall(aggs: list[dict], path: Path, styles: dict) -> bool:
    """Bars of tiny-object recall per cell, per scene that has recall."""
    scenes = _scenes_where(aggs, lambda a: a["recall_mean"] is not None)
    if not scenes:
        return False
    plt, fig, axes = _figure(len(scenes))
    for ax, (scene, cells) in zip(axes, scenes.items()):
        show_it = len({a["iterations"] for a in cells}) > 1
        x = np.arange(len(cells))
        ax.bar(x, [a["recall_mean"] for a in cells], yerr=[a["recall_std"] or 0.0 for a in cells],
               color=[styles[a["method"]][0] for a in cells], capsize=3)
        ax.set_xticks(x, [cell_label(a, show_it, short=True) for a in cells], rotation=30, ha="right", fontsize=8)
        ax.set_ylim(0, 1.05)
        ax.set_ylabel("recall (fraction of object-view pairs)")
        ax.set_title(scene)
        ax.grid(alpha=0.3, axis="y")
    _save(plt, fig, path, "Tiny-object recall (mean ± std over seeds)")
    return True


# ---------------------------------------------------------------------------- crops


def crop_window(cx: float, cy: float, size: int, width: int, height: int) -> tuple[int, int, int]:
    """Top-left ``(x0, y0)`` and side of a square window centred on the pixel-index centroid
    ``(cx, cy)`` (mean column, mean row of the object's pixels), moved inside the image;
    the side is ``size`` or the image's smaller side if that is less."""
    s = min(size, width, height)
    x0 = int(math.floor(cx + 0.5 - s / 2 + 0.5))
    y0 = int(math.floor(cy + 0.5 - s / 2 + 0.5))
    return min(max(x0, 0), width - s), min(max(y0, 0), height - s), s


def _read_rgb(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()


def _read_gt(path: Path, width: int, height: int) -> np.ndarray:
    """Ground truth at the evaluation resolution: PIL ``reduce`` by the integer factor."""
    from PIL import Image

    with Image.open(path) as im:
        im = im.convert("RGB")
        factor = max(im.width // width, 1)
        if factor > 1:
            im = im.reduce(factor, box=(0, 0, width * factor, height * factor))
        arr = np.asarray(im, dtype=np.uint8)
    if arr.shape[0] < height or arr.shape[1] < width:
        raise PromptGSError(f"{path}: image is {arr.shape[1]}x{arr.shape[0]}, smaller than the evaluation resolution {width}x{height}")
    return arr[:height, :width].copy()


def _read_mask(path: Path, width: int, height: int) -> np.ndarray:
    """Object ids [height, width] at the evaluation resolution (largest id per block)."""
    import torch

    from ..metrics import resize_mask
    from PIL import Image

    with Image.open(path) as im:
        arr = np.asarray(im)
    if arr.ndim == 3:
        arr = arr[..., :3].max(axis=-1)
    return resize_mask(torch.from_numpy(arr.astype(np.int64)), height, width).numpy()


def _mask_path(mask_dir: Path, image_name: str) -> Path | None:
    stem = Path(image_name).stem
    if (mask_dir / f"{stem}.png").is_file():
        return mask_dir / f"{stem}.png"
    matches = sorted(mask_dir.glob(stem + ".*"))
    return matches[0] if matches else None


def choose_pairs(candidates: list[dict], max_pairs: int) -> list[dict]:
    """Pick (view, object) pairs: the largest view of each object first (largest objects
    first), then the remaining pairs by size. Each candidate has ``size``, ``image``, ``object``."""
    ordered = sorted(candidates, key=lambda c: (-c["size"], c["image"], c["object"]))
    chosen, seen = [], set()
    for c in ordered:
        if c["object"] not in seen:
            seen.add(c["object"])
            chosen.append(c)
    chosen += [c for c in ordered if c not in chosen]
    return chosen[:max_pairs]


def compose_crop_sheet(titles: list[str], rows: list[tuple[str, list[np.ndarray | None]]], scale: int):
    """A PIL image: a title row, then per row its label and its crops upscaled ×scale with
    nearest neighbour (None = mid-grey "no render" cell). All crops are the same size."""
    from PIL import Image, ImageDraw

    side = next(c.shape[0] for _, crops in rows for c in crops if c is not None)
    pitch = side * scale + CROP_GAP
    width = CROP_LABEL_W + CROP_GAP + len(titles) * pitch
    height = CROP_HEADER_H + CROP_GAP + len(rows) * pitch
    sheet = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(sheet)
    for j, title in enumerate(titles):
        draw.text((CROP_LABEL_W + CROP_GAP + j * pitch, 3), title, fill="black")
    for i, (label, crops) in enumerate(rows):
        y = CROP_HEADER_H + CROP_GAP + i * pitch
        draw.text((3, y + 3), label, fill="black")
        for j, crop in enumerate(crops):
            x = CROP_LABEL_W + CROP_GAP + j * pitch
            if crop is None:
                draw.rectangle((x, y, x + side * scale - 1, y + side * scale - 1), fill=(128, 128, 128))
                draw.text((x + 3, y + 3), "no render", fill="white")
                continue
            big = np.repeat(np.repeat(crop, scale, axis=0), scale, axis=1)
            sheet.paste(Image.fromarray(big), (x, y))
    return sheet


def crop_sheet(scene_rows: list[dict], window: int = 24, scale: int = 6, max_pairs: int = 8):
    """The crop sheet of one scene's ok rows, or ``(None, reason)`` when it cannot be made.

    Columns: ground truth, then per method the render of its lowest-seed, no-budget cell
    at the scene's largest iteration count. Rows: up to ``max_pairs`` (view, object) pairs,
    from the test views' "objects" (visible objects) when the metrics have them, else every
    object in the masks. Returns ``(image, None)`` or ``(None, reason)``.
    """
    ok = [r for r in scene_rows if r["status"] == "ok"]
    if not ok:
        return None, "no finished cells"
    dataset = Path(ok[0]["dataset"])
    mask_dir = dataset / "object_masks"
    if not mask_dir.is_dir():
        return None, f"no object masks ({mask_dir})"
    top = max(int(r["iterations"]) for r in ok)
    picks: dict[str, dict] = {}
    for r in sorted(ok, key=lambda r: r["seed"]):
        if r.get("budget") is None and int(r["iterations"]) == top and r.get("run_dir"):
            picks.setdefault(r["method"], r)
    methods = sorted(picks, key=_method_rank)
    metrics = None
    for m in methods:
        try:
            metrics = json.loads((Path(picks[m]["run_dir"]) / "metrics.json").read_text())
            break
        except (OSError, json.JSONDecodeError):
            continue
    if metrics is None:
        return None, "no readable metrics.json in the no-budget run folders"
    width, height = (int(v) for v in metrics["resolution"])
    per_image = metrics.get("per_image", [])
    methods = [m for m in methods if (Path(picks[m]["run_dir"]) / "renders").is_dir()]
    if not methods:
        return None, "no run folder kept its test renders (renders/)"
    use_objects = any("objects" in row for row in per_image)
    candidates = []
    for row in per_image:
        mpath = _mask_path(mask_dir, row["image"])
        if mpath is None:
            continue
        ids = _read_mask(mpath, width, height)
        allowed = {int(k) for k in row.get("objects", {})} if use_objects else None
        for obj in np.unique(ids):
            if obj == 0 or (allowed is not None and int(obj) not in allowed):
                continue
            ys, xs = np.nonzero(ids == obj)
            candidates.append({"image": row["image"], "object": int(obj), "size": len(xs),
                               "cx": float(xs.mean()), "cy": float(ys.mean())})
    pairs = choose_pairs(candidates, max_pairs)
    if not pairs:
        return None, "no object in the test views' masks"
    images_dir = dataset / (ok[0].get("images") or "images")
    gts: dict[str, np.ndarray] = {}
    renders: dict[tuple[str, str], np.ndarray | None] = {}
    rows = []
    for p in pairs:
        name, stem = p["image"], Path(p["image"]).stem
        if name not in gts:
            gts[name] = _read_gt(images_dir / name, width, height)
        x0, y0, s = crop_window(p["cx"], p["cy"], window, width, height)
        crops: list[np.ndarray | None] = [gts[name][y0:y0 + s, x0:x0 + s]]
        for m in methods:
            if (m, name) not in renders:
                path = Path(picks[m]["run_dir"]) / "renders" / f"{stem}.png"
                img = _read_rgb(path) if path.is_file() else None
                renders[(m, name)] = img if img is not None and img.shape[:2] == (height, width) else None
            img = renders[(m, name)]
            crops.append(None if img is None else img[y0:y0 + s, x0:x0 + s])
        rows.append((f"{stem} #{p['object']}", crops))
    return compose_crop_sheet(["ground truth"] + [method_name(m) for m in methods], rows, scale), None


# ---------------------------------------------------------------------------- report


def write_report(results: Path, out: Path, crop_px: int = 24, crop_scale: int = 6) -> dict:
    """Write the charts, table.md, crop sheets and summary.json for a results file into ``out``.

    Returns ``{"files": [Path, ...], "aggregate": [...], "failed": [...], "notes": [...]}``;
    ``notes`` says what was not written and why. Raises PromptGSError for a bad results
    file or one with no rows.
    """
    results, out = Path(results), Path(out)
    rows = current_rows(load_results(results))
    if not rows:
        raise PromptGSError(f"{results}: no result rows")
    out.mkdir(parents=True, exist_ok=True)
    aggs = aggregate(rows)
    failed = [r for r in rows if r["status"] == "error"]
    styles = method_styles(r["method"] for r in rows)
    files: list[Path] = []
    notes: list[str] = []

    charts = [
        ("psnr_vs_time.png", lambda p: plot_quality_vs_time(aggs, "psnr", p, "PSNR (dB)", styles), "no finished cell"),
        ("masked_psnr_vs_time.png",
         lambda p: plot_quality_vs_time(aggs, "masked_psnr", p, "masked PSNR (dB)", styles), "no scene has object masks"),
        ("psnr_vs_gaussians.png", lambda p: plot_psnr_vs_gaussians(aggs, p, styles), "no finished cell"),
        ("recall.png", lambda p: plot_recall(aggs, p, styles), "no scene has recall"),
        ("compaction.png", lambda p: plot_compaction(aggs, p, styles), "no method was run with and without +compact"),
    ]
    for name, draw, why_not in charts:
        if draw(out / name):
            files.append(out / name)
        else:
            notes.append(f"{name} not written: {why_not}")

    loads: dict[str, list[float]] = {}
    for r in rows:
        if isinstance(r.get("load_avg"), (int, float)):
            loads.setdefault(r["scene"], []).append(float(r["load_avg"]))
    (out / "table.md").write_text(table_markdown(aggs, failed, loads), encoding="utf-8")
    files.append(out / "table.md")

    first_sheet = None
    for scene in dict.fromkeys(r["scene"] for r in rows):
        try:
            sheet, why = crop_sheet([r for r in rows if r["scene"] == scene], crop_px, crop_scale)
        except (OSError, KeyError, ValueError, PromptGSError) as exc:
            sheet, why = None, f"{type(exc).__name__}: {exc}"
        if sheet is None:
            notes.append(f"crops_{scene}.png not written: {why}")
            continue
        path = out / f"crops_{scene}.png"
        sheet.save(path)
        files.append(path)
        if first_sheet is None:
            first_sheet = sheet
            sheet.save(out / "crops.png")
            files.append(out / "crops.png")
    if first_sheet is None:
        notes.append("crops.png not written: no scene with object masks and kept renders")

    files.append(out / "summary.json")
    summary = {
        "schema": "promptgs-report/1",
        "results": str(results),
        "aggregate": aggs,
        "failed": [{"cell": r["cell"], "error": r.get("error")} for r in failed],
        "files": [p.name for p in files],
        "notes": notes + [LPIPS_NOTE],
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
    return {"files": files, "aggregate": aggs, "failed": failed, "notes": notes}


# ---------------------------------------------------------------------------- command line


def add_parser(subparsers: Any) -> None:
    """Register the ``report`` subcommand on an argparse subparsers object."""
    p = subparsers.add_parser(
        "report",
        help="charts and tables from benchmark results (RESULTS.jsonl)",
        description="Read the JSON-lines results of `promptgs bench` and write speed–accuracy charts, "
        "Markdown tables, tiny-object crop sheets and summary.json into --out.",
    )
    p.add_argument("results", type=Path, help="results file written by promptgs bench (JSON lines)")
    p.add_argument("--out", type=Path, required=True, help="folder to write the report into")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``promptgs report``; returns the exit status."""
    try:
        report = write_report(args.results, args.out)
    except PromptGSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for path in report["files"]:
        print(f"wrote {path}")
    for note in report["notes"]:
        print(f"note: {note}")
    return 0
