"""MkDocs hooks (mkdocs.yml `hooks:`): generated parameter tables and a nav that follows docs/.

- A line `<!-- params: vpr_node -->` (or `posegraph_node`) in a page becomes the node's parameter
  table, rendered from the one table in `pair_vpr_ros/params/table.py` (`params/posegraph.py`),
  so the docs never restate a default, range or description by hand.
- Nav entries whose page does not exist yet are dropped (pages other work adds are listed ahead),
  and a page of docs/ that the nav does not name is added under "More".
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the package of this checkout, also without `pip install -e`
    sys.path.insert(0, str(ROOT))

MARKER = re.compile(r"^<!-- params: (\w+) -->$", re.M)


def _tables() -> dict[str, tuple]:
    from pair_vpr_ros.params.posegraph import PARAMS as POSEGRAPH_PARAMS
    from pair_vpr_ros.params.table import PARAMS

    return {"vpr_node": PARAMS, "posegraph_node": POSEGRAPH_PARAMS}


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return "[" + ", ".join(f"{float(v):g}" for v in value) + "]"
    if isinstance(value, str):
        return f'"{value}"'
    return f"{value:g}" if isinstance(value, float) else str(value)


def _kind(default: Any) -> str:
    if isinstance(default, tuple):
        return f"double[{len(default)}]"
    return {bool: "bool", int: "int", float: "double", str: "string"}[type(default)]


def params_table(table: tuple) -> str:
    """A Markdown table of `ParamSpec`s: name, type, default, allowed values, when, meaning."""
    rows = [
        "| parameter | type | default | allowed | changes | description |",
        "|---|---|---|---|---|---|",
    ]
    for p in table:
        if p.choices:
            allowed = ", ".join(f"`{c}`" for c in p.choices)
        elif p.low is not None:
            allowed = f"{_value(p.low)} .. {_value(p.high)}"
        else:
            allowed = ""
        when = "start-up" if p.read_only else "run time"
        text = p.description.replace("|", "\\|")
        rows.append(
            f"| `{p.name}` | {_kind(p.default)} | `{_value(p.default)}` | {allowed} | {when} "
            f"| {text} |"
        )
    return "\n".join(rows) + "\n"


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    tables = _tables()

    def render(match: re.Match) -> str:
        name = match[1]
        if name not in tables:
            raise ValueError(f"{page.file.src_path}: no parameter table named {name!r}")
        return params_table(tables[name])

    return MARKER.sub(render, markdown)


def _prune(nav: list, docs: Path) -> list:
    out = []
    for item in nav:
        if isinstance(item, dict):
            ((title, value),) = item.items()
            if isinstance(value, list):
                value = _prune(value, docs)
                if value:
                    out.append({title: value})
            elif "://" in value or (docs / value).is_file():
                out.append(item)
        elif "://" in item or (docs / item).is_file():
            out.append(item)
    return out


def _named(nav: list) -> set[str]:
    found = set()
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        found |= _named(value) if isinstance(value, list) else {value}
    return found


def on_config(config: Any) -> Any:
    docs = Path(config["docs_dir"])
    nav = _prune(config["nav"] or [], docs)
    named = _named(nav)
    more = sorted(p.relative_to(docs).as_posix() for p in docs.rglob("*.md"))
    more = [p for p in more if p not in named]
    if more:
        nav.append({"More": more})
    config["nav"] = nav
    return config
