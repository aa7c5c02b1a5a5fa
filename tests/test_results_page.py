"""The results page and the README's table are what results/*.json give, and the docs' links resolve.

`tools/results_page.py` renders docs/results.md and the README's marked table from the
JSON files of results/; these tests fail when the committed pages disagree with the files,
check the summaries the tool computes, and check that every relative link of the README
and docs/ points at a file (and a heading) that exists.
"""

from __future__ import annotations

import copy
import importlib.util
import json
import re
import shutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _load_tool():
    spec = importlib.util.spec_from_file_location("results_page", REPO / "tools" / "results_page.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


rp = _load_tool()


def _copy_pages(dest: Path) -> Path:
    """A repository-shaped folder with the results, the README and the page."""
    shutil.copytree(REPO / "results", dest / "results")
    (dest / "docs").mkdir()
    shutil.copy(REPO / "docs" / "results.md", dest / "docs" / "results.md")
    shutil.copy(REPO / "README.md", dest / "README.md")
    return dest


def _seeds_table(cells, runs=("a",)):
    return {
        "title": "T", "order": 1, "kind": "seeds", "summary": "s", "protocol": "p",
        "runs": [{"id": r, "commit": "abc1234", "machine": "m", "command": ["c"]} for r in runs],
        "baseline": "base",
        "methods": [{"id": "base", "label": "Base"}, {"id": "new", "label": "New", "run": runs[-1]}],
        "scenes": [{"id": "s", "label": "S"}],
        "cells": cells,
    }


def _cell(method, seed, psnr, n, seconds, run="a", recall=None, masked=None):
    return {"run": run, "scene": "s", "method": method, "seed": seed, "psnr": psnr,
            "masked_psnr": masked, "recall": recall, "n_gaussians": n, "train_seconds": seconds}


def test_the_results_page_and_the_readme_table_are_up_to_date():
    assert rp.stale_files(REPO) == [], "run python tools/results_page.py"


def test_a_changed_figure_makes_the_readme_and_the_page_stale_until_regenerated(tmp_path):
    repo = _copy_pages(tmp_path)
    assert rp.stale_files(repo) == []
    path = repo / "results" / "mountain_1500.json"
    table = json.loads(path.read_text())
    before = rp.render_table(table)
    cell = next(c for c in table["cells"] if c["method"] == "promptgs-1" and c["seed"] == 0)
    cell["psnr"] += 6.0  # the row's mean rises by 1 dB
    path.write_text(json.dumps(table))
    assert rp.render_table(table) != before
    assert set(rp.stale_files(repo)) == {Path("README.md"), Path("docs/results.md")}
    assert rp.main(["--check", "--repo", str(repo)]) == 1
    assert rp.main(["--repo", str(repo)]) == 0
    assert rp.stale_files(repo) == []
    assert "36.66 ±" in (repo / "README.md").read_text()


def test_a_seed_table_gives_means_spreads_recall_and_ratios_to_the_baseline():
    table = _seeds_table([
        _cell("base", 0, 30.0, 1000, 10.0, recall=0.0, masked=18.0),
        _cell("base", 1, 31.0, 3000, 12.0, recall=0.0, masked=18.0),
        _cell("new", 0, 32.0, 500, 20.0, recall=0.5, masked=28.0),
        _cell("new", 1, 33.0, 1800, 36.0, recall=0.75, masked=29.0),
    ])
    rows = rp.render_table(table).splitlines()
    assert rows[0] == ("| method | PSNR (dB) | masked PSNR (dB) | recall, seeds 0, 1 (mean) "
                       "| Gaussians (× Base) | training time (× Base) |")
    assert rows[2] == "| Base | 30.50 ± 0.50 | 18.00 ± 0.00 | 0.00 / 0.00 (0.000) | 2.0k | 10–12 s |"
    # Ratios seed by seed: Gaussians 0.50 and 0.60, time 2.00 and 3.00 (median 2.50).
    assert rows[3] == "| New | 32.50 ± 0.50 | 28.50 ± 0.50 | 0.50 / 0.75 (0.625) | 0.50–0.60× | 2.50× (2.00–3.00) |"


def test_a_method_from_another_run_is_compared_with_the_baseline_of_its_own_run():
    table = _seeds_table([
        _cell("base", 0, 30.0, 1000, 10.0, run="a"),
        _cell("base", 0, 30.0, 1000, 40.0, run="b"),  # the same model, timed in another run
        _cell("new", 0, 32.0, 800, 80.0, run="b"),
    ], runs=("a", "b"))
    rows = rp.render_table(table).splitlines()
    assert rows[2] == "| Base | 30.00 ± 0.00 | 1.0k | 10 s |"  # the first run's row
    assert rows[3] == "| New | 32.00 ± 0.00 | 0.80× | 2.00× |"  # 80 s against run b's 40 s


def test_a_missing_baseline_cell_is_an_error_naming_the_run_and_seed():
    table = _seeds_table([_cell("base", 0, 30.0, 1000, 10.0), _cell("new", 1, 31.0, 900, 12.0)])
    with pytest.raises(rp.ResultsError, match="no base cell for run a, scene s, seed 1"):
        rp.render_table(table)


def test_a_plain_table_formats_numbers_by_column_and_leaves_text_as_it_is():
    table = {"columns": [{"key": "name", "title": "name"},
                         {"key": "ms", "title": "ms", "format": ".1f"},
                         {"key": "n", "title": "count", "format": ","},
                         {"key": "x", "title": "ratio", "format": ".2f", "suffix": "×"}],
             "rows": [{"name": "a", "ms": 29.04, "n": 126056, "x": 1.5}, {"name": "b", "ms": None}]}
    assert rp.render_plain(table).splitlines()[2:] == ["| a | 29.0 | 126,056 | 1.50× |", "| b | – | – | – |"]


def test_a_bad_results_file_is_one_error_naming_the_file_and_the_key(tmp_path, capsys):
    repo = _copy_pages(tmp_path)
    path = repo / "results" / "stability.json"
    table = json.loads(path.read_text())
    del table["protocol"]
    path.write_text(json.dumps(table))
    with pytest.raises(rp.ResultsError, match=r"stability\.json: missing 'protocol'"):
        rp.load_tables(repo / "results")
    assert rp.main(["--check", "--repo", str(repo)]) == 2
    assert "results_page: error:" in capsys.readouterr().err


def test_every_results_file_names_its_commands_machine_and_protocol():
    tables = rp.load_tables(REPO / "results")
    assert "mountain_1500" in tables
    for name, table in tables.items():
        assert table["protocol"].strip(), name
        for run in table["runs"]:
            assert run["machine"].strip() and run["command"], (name, run["id"])
        if table["kind"] == "seeds":
            bad = copy.deepcopy(table)
            bad["cells"][0]["run"] = "nowhere"
            with pytest.raises(rp.ResultsError, match="is not one of 'runs'"):
                rp.validate(bad, Path(name))


def test_a_readme_without_the_marked_block_is_an_error():
    tables = rp.load_tables(REPO / "results")
    with pytest.raises(rp.ResultsError, match="no '<!-- results-table"):
        rp.readme_with_tables("# a README without the table\n", tables)


# ---- links ---------------------------------------------------------------------------

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
CODE = re.compile(r"`[^`\n]*`")
HEADING = re.compile(r"^#{1,6} +(.+?) *$", re.M)
DOCUMENTS = ["README.md", "CHANGELOG.md", "benchmarks/README.md", *sorted(
    str(p.relative_to(REPO)) for p in (REPO / "docs").glob("*.md"))]


def _links(text: str) -> list[str]:
    return LINK.findall(CODE.sub("", FENCE.sub("", text)))


def _anchors(markdown: Path) -> set[str]:
    return {rp.anchor(h) for h in HEADING.findall(FENCE.sub("", markdown.read_text()))}


def test_the_link_finder_sees_links_and_images_but_not_code():
    text = "[a](x.md) ![b](img/c.png) `[d](not.md)`\n```\n[e](nor.md)\n```\n[f](y.md#part)"
    assert _links(text) == ["x.md", "img/c.png", "y.md#part"]


@pytest.mark.parametrize("document", DOCUMENTS)
def test_every_relative_link_points_at_a_file_and_heading_that_exist(document):
    source = REPO / document
    missing = []
    for target in _links(source.read_text()):
        if re.match(r"[a-z]+:", target):
            continue  # http(s), mailto: not checked here
        path, _, fragment = target.partition("#")
        resolved = (source.parent / path).resolve() if path else source
        if not resolved.exists():
            missing.append(target)
        elif fragment and resolved.suffix == ".md" and fragment not in _anchors(resolved):
            missing.append(target)
    assert missing == [], f"{document}: links to nothing: {missing}"
