"""Figures and settings the docs quote match their one source, so a changed default cannot leave
a stale page: the demo's detector settings (config/demo.yaml), the node's loop outputs
(ros/outputs.py), and every image's caption says when and on what it was made.

A paragraph that dates itself (YYYY-MM-DD) is a record of that day and may quote what was then,
as may the paragraphs from one that says "the record of" (an older model) to the next heading;
any other paragraph speaks of now and must quote the current values."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
PAGES = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
NUMBER = r"(\d+(?:\.\d+)?)"
# how the pages quote the demo's settings -> the parameter of config/demo.yaml
QUOTES = {
    rf"pair(?: score)? \+ {NUMBER} x (?:global )?similarity": "global_weight",
    rf"`global_weight`:? {NUMBER}\b|global_weight: {NUMBER}\b": "global_weight",
    r"`top_k: (\d+)`|\btop (\d+) re-ranked|re-ranks the global top (\d+)\b": "top_k",
    rf"`score_threshold: {NUMBER}`|\bthreshold {NUMBER}\b": "score_threshold",
}
ABOUT_THE_DEMO = re.compile(r"config/demo\.yaml|shipped model|demo model")
WORDS = "zero one two three four five six seven eight nine ten".split()


def paragraphs(page: Path) -> list[str]:
    return re.split(r"\n\s*\n", page.read_text())


def demo_quotes() -> list[tuple[str, str, float, str]]:
    """(page, parameter, quoted value, excerpt) of every undated paragraph about the demo."""
    found = []
    for page in PAGES:
        record = False  # from "... the record of ..." to the next heading: an older model's
        for text in paragraphs(page):
            record = (record and not text.startswith("#")) or "the record of" in text
            if record or DATE.search(text) or not ABOUT_THE_DEMO.search(text):
                continue
            for pattern, name in QUOTES.items():
                for match in re.finditer(pattern, text.replace("\n", " ")):
                    value = float(next(g for g in match.groups() if g is not None))
                    found.append((page.name, name, value, match[0]))
    return found


def test_demo_settings_quoted_in_docs_are_config_demo_yaml():
    demo = yaml.safe_load((ROOT / "config/demo.yaml").read_text())["/**"]["ros__parameters"]
    quotes = demo_quotes()
    names = {name for _, name, _, _ in quotes}
    assert names == {"global_weight", "top_k", "score_threshold"} and len(quotes) >= 6
    stale = [q for q in quotes if q[2] != float(demo[q[1]])]
    assert stale == [], f"config/demo.yaml: {[(n, demo[n]) for n in sorted(names)]}"


def test_a_changed_setting_would_be_caught(monkeypatch, tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        "The demo model re-ranks by pair + 40 x similarity (`config/demo.yaml`).\n\n"
        "On 2026-11-25 the demo model re-ranked by pair + 40 x similarity.\n\n"
        "Below is the record of the old demo model.\n\nIt used `top_k: 1`.\n\n# Now\n\n"
        "The demo model checks `top_k: 3`.\n"
    )
    monkeypatch.setattr(f"{__name__}.PAGES", [page])
    assert demo_quotes() == [
        ("page.md", "global_weight", 40.0, "pair + 40 x similarity"),
        ("page.md", "top_k", 3.0, "`top_k: 3`"),
    ]


def loop_outputs() -> int:
    """vpr_node's loop topics: the base topic and each of ros/outputs.py's SUBTOPICS."""
    tree = ast.parse((ROOT / "pair_vpr_ros/ros/outputs.py").read_text())
    table = next(
        n.value
        for n in tree.body
        if isinstance(n, ast.Assign) and ast.unparse(n.targets[0]) == "SUBTOPICS"
    )
    pairs = next(n for n in ast.walk(table) if isinstance(n, ast.Tuple) and len(n.elts) > 2)
    return 1 + len(pairs.elts)


def test_quoted_output_counts_are_the_nodes():
    count = loop_outputs()
    node = (ROOT / "docs/node.md").read_text()
    assert len(re.findall(r"^\| `loop_closure[`/]", node, re.M)) == count == 7
    claims = [
        (page.name, m[0])
        for page in PAGES
        for m in re.finditer(rf"\b({'|'.join(WORDS)}|\d+) (?:loop )?outputs\b", page.read_text())
    ]
    assert [c for c in claims if c[1].split()[0] not in (WORDS[count], str(count))] == []


def test_every_image_has_a_caption_with_its_date_and_machine():
    """The line after an image (past blank lines) is an italic caption with a date and the
    machine (development machine / VM, or a GPU)."""
    missing = []
    for page in PAGES:
        lines = page.read_text().splitlines()
        for i, line in enumerate(lines):
            if not re.match(r"\s*!\[[^\]]*\]\([^)]+\)", line):
                continue
            after = "\n".join(lines[i + 1 : i + 6]).strip()
            caption = after.split("\n\n")[0]
            dated = caption.startswith("*") and DATE.search(caption)
            if not (dated and re.search(r"machine|\bVM\b|GPU", caption)):
                missing.append(f"{page.name}:{i + 1}")
    assert missing == []
