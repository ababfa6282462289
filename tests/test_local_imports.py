"""An import inside a function is there to keep something heavy out of a process, and says so.

A function-local import of the house's packages (tests and bench aside) must defer a HEAVY module
that the enclosing module does not already load when it is imported (its own top-level imports,
followed through the project's modules): torch in the daemon, Flask in a CLI command, SQLAlchemy
in `run_trainer.py --help`. Anything else goes to the top of the module, where tests/test_layers.py
and a reader see it. Each one carries its reason in a comment on its line or the line above
(`# lazy: loads torch`, or a sentence); a group of such imports one under the other may share the
comment of its first. An import tried for an optional dependency (`try: ... except ImportError`)
is local by nature; it says why too.
"""
from __future__ import annotations

import ast
from pathlib import Path

from test_layers import REPO, _is_project_module, _module_name, _resolve, project_files

# What is worth not importing: hundreds of MB (torch, the simulator), a server stack a command
# does not serve with (Flask, Socket.IO, Celery, Redis), a database layer, the numeric and file
# format libraries a torch-free path does not touch.
HEAVY = frozenset({"torch", "dm_control", "mujoco", "celery", "kombu", "flask", "flask_socketio", "engineio",
                   "socketio", "sqlalchemy", "alembic", "numpy", "safetensors", "mcap", "redis", "PIL", "av",
                   "playwright", "psutil"})


def top_level_imports(files: list[Path], root: Path) -> dict[str, set[str]]:
    """module -> the modules its top level imports (a `try:` block's too)."""
    top: dict[str, set[str]] = {}
    for path in files:
        found: set[str] = set()
        for node in ast.parse(path.read_text()).body:
            for n in (node.body if isinstance(node, ast.Try) else [node]):
                if isinstance(n, ast.Import):
                    found |= {a.name for a in n.names}
                elif isinstance(n, ast.ImportFrom):
                    base = _resolve(path, n, root) if n.level else (n.module or "")
                    found |= {f"{base}.{a.name}" if _is_project_module(f"{base}.{a.name}", root) else base
                              for a in n.names}
        top[_module_name(path, root)] = found
    return top


def loads(module: str, top: dict[str, set[str]], seen: set[str] | None = None) -> set[str]:
    """The top-level packages importing `module` loads (its parents' imports included)."""
    seen = set() if seen is None else seen
    if module in seen:
        return set()
    seen.add(module)
    parts = module.split(".")
    out: set[str] = set()
    for i in range(1, len(parts)):
        out |= loads(".".join(parts[:i]), top, seen)
    if module not in top:
        return out | {parts[0]}
    for imported in top[module]:
        out |= loads(imported, top, seen)
    return out


def _optional(tree: ast.AST) -> set[int]:
    """The imports tried in a `try:` whose handler catches ImportError (an optional dependency)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and any(
                isinstance(h.type, ast.Name) and h.type.id in ("ImportError", "ModuleNotFoundError")
                for h in node.handlers):
            out |= {id(n) for n in node.body if isinstance(n, (ast.Import, ast.ImportFrom))}
    return out


def _has_reason(node: ast.AST, lines: list[str], imports_at: set[int]) -> bool:
    """A comment on the import's lines, or above it, or above the group of imports it ends."""
    if any("#" in lines[i - 1] for i in range(node.lineno, node.end_lineno + 1)):
        return True
    line = node.lineno - 1
    while line >= 1:
        text = lines[line - 1].strip()
        if text.startswith("#"):
            return True
        if line not in imports_at or not text:
            return False
        if "#" in text:
            return True
        line -= 1
    return False


def local_import_problems(files: list[Path], root: Path) -> list[str]:
    top = top_level_imports(files, root)
    problems = []
    for path in files:
        rel = path.relative_to(root).as_posix()
        lines = path.read_text().splitlines()
        tree = ast.parse("\n".join(lines))
        own = loads(_module_name(path, root), top) & HEAVY
        nodes = {id(n): n for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                 for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))}
        optional = _optional(tree)
        imports_at = {i for n in nodes.values() for i in range(n.lineno, n.end_lineno + 1)}
        for node in sorted(nodes.values(), key=lambda n: n.lineno):
            if isinstance(node, ast.Import):
                modules = [a.name for a in node.names]
            else:
                base = _resolve(path, node, root) if node.level else (node.module or "")
                modules = [f"{base}.{a.name}" if _is_project_module(f"{base}.{a.name}", root) else base
                           for a in node.names]
            deferred = set().union(*(loads(m, top) for m in modules)) & HEAVY - own
            where = f"{rel}:{node.lineno}"
            if not deferred and id(node) not in optional:
                problems.append(f"{where}: {', '.join(modules)} defers nothing heavy this module does not load "
                                "already: import it at the top")
            elif not _has_reason(node, lines, imports_at):
                why = f"it defers {', '.join(sorted(deferred))}" if deferred else "an optional dependency"
                problems.append(f"{where}: say why it is local ({why}) in a comment on its line or the line above")
    return problems


def test_every_function_local_import_defers_something_heavy_and_says_why():
    problems = local_import_problems(project_files(), REPO)
    assert not problems, "\n".join(problems)


def test_the_rule_on_made_up_modules(tmp_path):
    def fake(rel: str, text: str) -> Path:
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        return path

    fake("daemon/__init__.py", "")
    light = fake("daemon/light.py", "import json\n")
    heavy = fake("daemon/heavy.py", "import torch\n")
    uses = fake("daemon/uses.py", (
        "import numpy\n"
        "def a():\n    from daemon import light\n"          # 3: nothing heavy: move it
        "def b():\n    from daemon import heavy\n"          # 5: torch, no reason given
        "def c():\n    import numpy as np  # lazy\n"        # 7: numpy is loaded already
        "def d():\n    # keeps torch out of the daemon\n    from daemon import heavy\n"  # 10: fine
        "def e():\n    from daemon import heavy  # torch\n    import torch.nn\n"  # 13: the group's comment
        "def f():\n    try:\n        import zstandard\n    except ImportError:\n        pass\n"  # 16: why?
        "def g():\n    try:\n        import lz4  # optional\n    except ImportError:\n        pass\n"))
    problems = local_import_problems([tmp_path / "daemon/__init__.py", light, heavy, uses], tmp_path)
    assert [p.split(":")[1] for p in problems] == ["3", "5", "7", "16"], problems
    assert "import it at the top" in problems[0] and "defers torch" in problems[1]
