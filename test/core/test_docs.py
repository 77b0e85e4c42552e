"""The README and the documentation site's sources (the site itself: `make docs`, strict).

`mkdocs build --strict` checks every link, anchor and image inside docs/; the README is not part
of the site, so its links are checked here, as are the generated parameter tables and the nav.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import yaml

from pair_vpr_ros.params.posegraph import PARAMS as POSEGRAPH_PARAMS
from pair_vpr_ros.params.table import PARAMS

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"


def hooks():
    spec = importlib.util.spec_from_file_location("mkdocs_hooks", ROOT / "scripts/mkdocs_hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_is_short_and_keeps_the_two_commands():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    block = re.search(r"```bash\n(make demo .*?)```", text, re.S)[1]
    assert [line.split("#")[0].strip() for line in block.splitlines()] == [
        "make demo",
        "make test",
    ]


def test_every_relative_link_and_image_of_the_readme_resolves():
    text = (ROOT / "README.md").read_text()
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    local = [t for t in targets if "://" not in t]
    assert len(local) >= 10
    for target in local:
        path, _, anchor = target.partition("#")
        assert (ROOT / path).is_file(), target
        if anchor:  # a heading of that page, as MkDocs makes anchors (lower case, dashes)
            headings = re.findall(r"^#+ (.+)$", (ROOT / path).read_text(), re.M)
            slugs = {
                re.sub(r"[^\w\- ]", "", h).strip().lower().replace(" ", "-") for h in headings
            }
            assert anchor in slugs, target


def test_the_parameter_tables_are_generated_from_the_one_table():
    module = hooks()
    for name, table in (("vpr_node", PARAMS), ("posegraph_node", POSEGRAPH_PARAMS)):
        page = module.on_page_markdown(f"<!-- params: {name} -->\n", None, None, None)
        rows = re.findall(r"^\| `(\w+)` \| (\S+) \| `([^`]*)` \|", page, re.M)
        assert [r[0] for r in rows] == [p.name for p in table]
    rows = {}
    for line in module.params_table(PARAMS).splitlines()[2:]:
        cells = [c.strip() for c in line.strip("|").split(" | ")]
        rows[cells[0].strip("`")] = cells[1:]
    assert rows["top_k"][:4] == ["int", "`0`", "0 .. 1000", "run time"]
    assert rows["weights"][:4] == ["string", '`""`', "", "start-up"]
    assert rows["precision"][2] == "`fp32`, `int8`, `bf16`, `fp16`"
    pages = {"node.md": "vpr_node", "posegraph.md": "posegraph_node"}
    for page, name in pages.items():
        assert f"<!-- params: {name} -->" in (DOCS / page).read_text()


def test_the_nav_drops_pages_not_written_yet_and_adds_unlisted_ones(tmp_path):
    (tmp_path / "a.md").write_text("# a\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.md").write_text("# b\n")
    nav = [{"Home": "a.md"}, {"Later": [{"T": "training.md"}]}, "gone.md"]
    config = hooks().on_config({"docs_dir": str(tmp_path), "nav": nav})
    assert config["nav"] == [{"Home": "a.md"}, {"More": ["sub/b.md"]}]


def test_the_nav_holds_the_pages_the_issue_asks_for():
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    config["docs_dir"] = str(DOCS)
    nav = hooks().on_config(config)["nav"]
    named = hooks()._named(nav)
    wanted = {"index.md", "install.md", "node.md", "launch.md", "replay.md", "relative-pose.md",
              "posegraph.md", "evaluation.md", "bad-input.md", "performance.md",
              "ARCHITECTURE.md", "api.md"}  # fmt: skip
    assert wanted <= named, wanted - named
    assert named == {p.name for p in DOCS.glob("*.md")}  # unlisted pages land under "More"
