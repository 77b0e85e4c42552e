"""Each test file runs alone (`pytest test/<dir>/<file>`): every fixture a test file asks for is
defined in the file, imported into it by name, or in a conftest.py on its path -- never only
in another test module that happens to be collected first. Checked from the source's AST (fast);
`scripts/each_test_file.sh` runs every file alone (slow, by hand)."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

TEST = Path(__file__).resolve().parents[1]
# pytest's own fixtures (the ones these tests may ask for)
BUILTIN = {
    "request", "tmp_path", "tmp_path_factory", "tmpdir", "tmpdir_factory", "capsys",
    "capsysbinary", "capfd", "capfdbinary", "caplog", "monkeypatch", "recwarn", "pytestconfig",
    "record_property", "record_xml_attribute", "record_testsuite_property", "cache",
    "doctest_namespace", "pytester", "subtests",
}  # fmt: skip


def _is_fixture(decorator: ast.expr) -> bool:
    target = decorator.func if isinstance(decorator, ast.Call) else decorator
    return ast.unparse(target) in ("pytest.fixture", "fixture")


def _mark_strings(decorators: list[ast.expr], mark: str) -> set[str]:
    """Names in `@pytest.mark.<mark>("a, b", ...)` (parametrize: its first argument)."""
    names: set[str] = set()
    for d in decorators:
        if isinstance(d, ast.Call) and ast.unparse(d.func) == f"pytest.mark.{mark}" and d.args:
            args = d.args[:1] if mark == "parametrize" else d.args
            for arg in args:
                values = arg.elts if isinstance(arg, ast.Tuple | ast.List) else [arg]
                for v in values:
                    if isinstance(v, ast.Constant) and isinstance(v.value, str):
                        names |= {n.strip() for n in v.value.split(",") if n.strip()}
    return names


def _functions(tree: ast.Module):
    """(function, decorators of it and its class) for every function of the module."""
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            yield node, node.decorator_list
        elif isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    yield item, item.decorator_list + node.decorator_list


_PARSING: set[Path] = set()  # import cycles between test modules


@functools.cache
def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text())


@functools.cache
def fixtures_of(path: Path) -> frozenset[str]:
    """Fixtures a module defines, or imports by name from a helper module of test/ that does."""
    _PARSING.add(path)
    try:
        return frozenset(_fixtures_of(path))
    finally:
        _PARSING.discard(path)


def _fixtures_of(path: Path) -> set[str]:
    tree = _tree(path)
    found = {f.name for f, decorators in _functions(tree) if any(map(_is_fixture, decorators))}

    def lent(module: str) -> set[str]:
        for folder in (path.parent, TEST):
            helper = folder / (module.replace(".", "/") + ".py")
            if helper.is_file() and helper not in _PARSING:
                return set(fixtures_of(helper))
        return set()

    aliases: dict[str, str] = {}
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            defined = lent(node.module)
            found |= {a.asname or a.name for a in node.names if a.name in defined}
        elif isinstance(node, ast.Import):
            aliases |= {a.asname or a.name: a.name for a in node.names}
        elif (  # `saved = persist_tests.saved`: a fixture of an imported module, by name
            isinstance(node, ast.Assign)
            and isinstance(value := node.value, ast.Attribute)
            and isinstance(value.value, ast.Name)
            and value.value.id in aliases
            and value.attr in lent(aliases[value.value.id])
        ):
            found |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    return found


def used_fixtures(path: Path) -> set[str]:
    """Fixtures the tests and fixtures of `path` ask for (arguments without a default)."""
    tree = _tree(path)
    used: set[str] = set()
    for f, decorators in _functions(tree):
        if not (f.name.startswith("test") or any(map(_is_fixture, decorators))):
            continue
        args = [*f.args.posonlyargs, *f.args.args]
        plain = args[: len(args) - len(f.args.defaults)] + [
            a for a, d in zip(f.args.kwonlyargs, f.args.kw_defaults, strict=True) if d is None
        ]
        params = _mark_strings(decorators, "parametrize")
        used |= {a.arg for a in plain if a.arg not in ("self", "cls")} - params
        used |= _mark_strings(decorators, "usefixtures")
    return used


def plugins_declared(path: Path) -> bool:
    """Whether the module sets `pytest_plugins` (a test module must not: fixtures of a plugin
    it names reach other modules only when it happens to be collected first)."""
    tree = _tree(path)
    return any(
        isinstance(node, ast.Assign)
        and any(ast.unparse(t) == "pytest_plugins" for t in node.targets)
        for node in tree.body
    )


def missing_fixtures(path: Path, root: Path = TEST) -> set[str]:
    """Fixtures `path` asks for that neither it nor a conftest.py on its path provides."""
    available = BUILTIN | fixtures_of(path)
    for folder in [path.parent, *path.parent.parents]:
        if (folder / "conftest.py").is_file():
            available |= fixtures_of(folder / "conftest.py")
        if folder == root:
            break
    return used_fixtures(path) - available


def test_every_fixture_a_test_file_uses_is_reachable_when_it_runs_alone():
    files = sorted(TEST.glob("*/test_*.py"))
    assert len(files) > 100
    missing = {str(f.relative_to(TEST)): sorted(missing_fixtures(f)) for f in files}
    problems = {name: fixtures for name, fixtures in missing.items() if fixtures}
    assert problems == {}, "define these fixtures in the file or a conftest.py on its path"
    assert [f.name for f in files if plugins_declared(f)] == []


def test_the_check_finds_a_fixture_only_another_module_defines(tmp_path):
    (tmp_path / "conftest.py").write_text("import pytest\n@pytest.fixture\ndef shared(): ...\n")
    (tmp_path / "helper.py").write_text("import pytest\n@pytest.fixture\ndef imported(): ...\n")
    (tmp_path / "test_other.py").write_text("import pytest\n@pytest.fixture\ndef lent(): ...\n")
    mine = tmp_path / "test_mine.py"
    mine.write_text(
        "import pytest\nimport helper as h\nfrom helper import imported\nalso = h.imported\n"
        "pytest_plugins = ['test_other']\n"
        "@pytest.fixture\ndef own(shared): ...\n"
        "@pytest.mark.parametrize('n', [1])\n"
        "def test_a(own, imported, also, lent, n, tmp_path, k=1): ...\n"
        "@pytest.mark.usefixtures('ghost')\nclass TestB:\n    def test_b(self, shared): ...\n"
    )
    assert missing_fixtures(mine, root=tmp_path) == {"lent", "ghost"}
    assert plugins_declared(mine)


def test_tests_mirror_the_source_tree():
    """test/<stage>/ holds the tests of pair_vpr_ros/<stage>/; test/core those of the top-level
    modules (errors, types, identity, ...) and the project-wide checks (architecture, docs,
    these). Test file names are unique across folders (pytest imports them by name)."""
    stages = {
        p.name for p in (TEST.parent / "pair_vpr_ros").iterdir() if (p / "__init__.py").exists()
    }
    folders = {p.parent.name for p in TEST.glob("*/test_*.py")}
    assert folders - stages == {"core"}
    names = [p.name for p in TEST.glob("*/test_*.py")]
    assert sorted({n for n in names if names.count(n) > 1}) == []


def unreachable_imports(path: Path, root: Path = TEST) -> set[str]:
    """Modules `path` imports by a test/ helper's name (test_*.py or a module of test/) that are
    neither beside it nor in test/ itself: found only when pytest happened to put another
    folder on the path first, so the file fails to import when it runs alone."""
    local = {p.stem for p in path.parent.glob("*.py")} | {p.stem for p in root.glob("*.py")}
    helpers = {p.stem for p in root.glob("*/*.py")} | {p.stem for p in root.glob("*.py")}
    names = set()
    for node in ast.walk(_tree(path)):
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
    return {n for n in names if n in helpers and n not in local}


def test_every_test_helper_a_file_imports_is_reachable_when_it_runs_alone():
    files = sorted(TEST.glob("*/test_*.py"))
    problems = {str(f.relative_to(TEST)): sorted(unreachable_imports(f)) for f in files}
    assert {name: mods for name, mods in problems.items() if mods} == {}, (
        "move what these files share into a module of test/ (e.g. test/loop_records.py)"
    )


def test_the_check_finds_a_helper_of_another_folder(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "shared.py").write_text("X = 1\n")
    (tmp_path / "a" / "test_one.py").write_text("def helper(): ...\n")
    mine = tmp_path / "b" / "test_two.py"
    mine.write_text("import numpy\nfrom shared import X\nfrom test_one import helper\n")
    assert unreachable_imports(mine, root=tmp_path) == {"test_one"}
