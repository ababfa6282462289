"""A file holds one thing and a function reads in one sitting: no module of the packages is over
MAX_LINES lines and no function over MAX_FUNCTION_LINES (docs/architecture.md says so; an
exception would be stated there and listed here, and there is none)."""
from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("hope_models", "registry", "daemon", "workers", "webapp", "hope_trainer")
MAX_LINES = 450
MAX_FUNCTION_LINES = 80


def sources() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py"))


def test_the_packages_have_sources():
    assert len(sources()) > 100 and all((REPO / pkg / "__init__.py").is_file() for pkg in PACKAGES)


def test_no_module_is_over_the_limit():
    long = [f"{p.relative_to(REPO)}: {n} lines" for p in sources()
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_LINES]
    assert not long, f"modules over {MAX_LINES} lines (split along a seam):\n" + "\n".join(long)


def test_no_function_is_over_the_limit():
    long = []
    for p in sources():
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{p.relative_to(REPO)}:{node.lineno} {node.name}: {n} lines")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(long)
