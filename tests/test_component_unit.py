"""A component is one unit: its folder (hope_models/components/<name>/) and its row in the table
(hope_models/components/__init__.py) are the only places that know it by name.

Read with ast, over every package of the house and run_trainer.py (tests aside):
- no comparison with a component's name outside hope_models/components (`c == "mid_loop"`,
  `name != "vqvae"`, `c in ("vqvae", "fast_loop")`): the house asks the spec (`reads_vqvae`,
  `tokenizer`, `acts`, ...) or a role (TOKENIZER, ACTOR, PREDICTOR);
- a component's name is a string of the code (docstrings and comments aside) in at most
  MAX_NAMING_FILES files outside the package: the deployment default of auto-trained components
  (settings.py) and file-format keys are what may remain.
The names are the table's own, so a fourth component is held to the same rules. Each rule's
reader is itself tested on a snippet it must catch.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from hope_models.components import ACTOR, COMPONENTS, PREDICTOR, TOKENIZER, UnknownComponent, spec_of

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("daemon", "workers", "hope_models", "webapp", "registry", "hope_trainer", "migrations")
INSIDE = "hope_models/components/"
MAX_NAMING_FILES = 3
PARTS = ("config.py", "layers.py", "model.py", "train.py", "numpy_form.py")


def house_files() -> list[Path]:
    return sorted([p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")] + [REPO / "run_trainer.py"])


def _is_name(node: ast.AST, names: frozenset[str]) -> bool:
    return isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names


def name_branches(source: str, names: frozenset[str]) -> list[int]:
    """Lines of the comparisons that ask a component by name."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Compare):
            continue
        parts = [node.left, *node.comparators]
        if any(_is_name(p, names) for p in parts):
            lines.append(node.lineno)
        elif any(isinstance(op, (ast.In, ast.NotIn)) for op in node.ops) and any(
                isinstance(p, (ast.Tuple, ast.List, ast.Set)) and any(_is_name(e, names) for e in p.elts)
                for p in parts):
            lines.append(node.lineno)
    return lines


def name_strings(source: str, names: frozenset[str]) -> list[int]:
    """Lines of the string constants (docstrings aside) that are a component's name."""
    tree = ast.parse(source)
    docs = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
                and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)):
            docs.add(id(body[0].value))
    return [n.lineno for n in ast.walk(tree) if _is_name(n, names) and id(n) not in docs]


NAMES = frozenset(COMPONENTS)


def test_the_readers_catch_what_they_look_for():
    names = frozenset({"vqvae", "mid_loop"})
    snippet = ('def f(c, run):\n    """mid_loop in a docstring is prose"""\n    if c == "vqvae":\n        pass\n'
               '    if run.component != "mid_loop" and c in ("x", "vqvae"):\n        pass\n'
               '    if c not in ["y", "mid_loop"]:\n        pass\n    return {"mid_loop": 1}, c == "other"\n')
    assert sorted(name_branches(snippet, names)) == [3, 5, 5, 7]
    assert sorted(name_strings(snippet, names)) == [3, 5, 5, 7, 9]


def test_no_code_outside_the_components_package_asks_a_component_by_name():
    found = []
    for path in house_files():
        rel = path.relative_to(REPO).as_posix()
        if rel.startswith(INSIDE):
            continue
        found += [f"{rel}:{line}" for line in name_branches(path.read_text(), NAMES)]
    assert not found, ("a comparison with a component's name; ask its spec (hope_models/components/spec.py) or "
                       "a role (TOKENIZER, ACTOR, PREDICTOR) instead:\n  " + "\n  ".join(found))


def test_a_component_is_named_in_a_handful_of_files_outside_its_folder():
    naming = {}
    for path in house_files():
        rel = path.relative_to(REPO).as_posix()
        if not rel.startswith(INSIDE):
            lines = name_strings(path.read_text(), NAMES)
            if lines:
                naming[rel] = lines
    assert len(naming) <= MAX_NAMING_FILES, (
        f"{len(naming)} files outside {INSIDE} name a component in their code (at most {MAX_NAMING_FILES}):\n  "
        + "\n  ".join(f"{f}: lines {ls}" for f, ls in sorted(naming.items())))


def test_every_row_of_the_table_is_a_whole_folder():
    for name, spec in COMPONENTS.items():
        folder = REPO / spec.package.replace(".", "/")
        assert spec.name == name and folder.is_dir(), (name, spec.package)
        missing = [p for p in PARTS if not (folder / p).is_file()]
        assert not missing, f"{folder}: missing {missing}"
        assert callable(spec.part("train").build), name
        assert spec.part("numpy_form").RUNTIME.name == name
        assert spec.reads_vqvae in ("never", "optional", "required")
    # the roles the house asks for are each exactly one component
    assert [TOKENIZER] == [n for n, s in COMPONENTS.items() if s.tokenizer]
    assert [ACTOR] == [n for n, s in COMPONENTS.items() if s.acts]
    assert [PREDICTOR] == [n for n, s in COMPONENTS.items() if s.predicts]
    assert COMPONENTS[TOKENIZER].reads_vqvae == "never"
    # the tokenizer trains first: the table's order is the chain's
    assert next(iter(COMPONENTS)) == TOKENIZER


def test_an_unknown_component_is_refused_with_the_valid_ones():
    with pytest.raises(UnknownComponent, match=r"'wings' is not one of " + ", ".join(COMPONENTS)):
        spec_of("wings")
    with pytest.raises(ValueError):
        spec_of(None)
