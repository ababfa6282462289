"""How much of the house asks a component by name, and how many imports hide inside functions.

    .venv/bin/python bench/house_counts.py        # this checkout

Prints the counts issue "A component is one unit" is measured by: comparisons of a component's name
(`== "mid_loop"`, `in ("vqvae", ...)`) per file, the files that name mid_loop inside and outside
hope_models, and the function-local imports (all, and those of the project's own modules). Read
with ast: comments and docstrings do not count as branches (they do count as naming mid_loop).
"""
from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1]
PKGS = ["daemon", "workers", "hope_models", "webapp", "registry", "hope_trainer", "migrations"]
NAMES = {"vqvae", "fast_loop", "mid_loop"}
OWN = {"daemon", "workers", "hope_models", "webapp", "registry", "hope_trainer"}
files = [p for pkg in PKGS for p in (ROOT / pkg).rglob("*.py")] + [ROOT / "run_trainer.py"]
branches: dict[str, int] = {}
mid_files: list[str] = []
local_imports = local_own = 0


def is_name_const(n: ast.AST) -> bool:
    return isinstance(n, ast.Constant) and n.value in NAMES


for f in files:
    text = f.read_text()
    rel = f.relative_to(ROOT)
    if "mid_loop" in text: mid_files.append(str(rel))
    tree = ast.parse(text)
    n = 0
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            parts = [node.left, *node.comparators]
            if any(is_name_const(p) for p in parts): n += 1
            elif any(isinstance(op, (ast.In, ast.NotIn)) for op in node.ops) and any(
                    isinstance(p, (ast.Tuple, ast.List, ast.Set)) and any(is_name_const(e) for e in p.elts) for p in parts):
                n += 1
    if n: branches[str(rel)] = n
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for sub in ast.walk(node):
                if isinstance(sub, (ast.Import, ast.ImportFrom)):
                    local_imports += 1
                    mod = (sub.module or "") if isinstance(sub, ast.ImportFrom) else sub.names[0].name
                    if mod.split(".")[0] in OWN: local_own += 1
print("component-name branches:", sum(branches.values()), "in", len(branches), "files,",
      len({p.split('/')[0] for p in branches}), "packages")
for k, v in sorted(branches.items(), key=lambda kv: -kv[1])[:40]: print("  ", v, k)
outside = [m for m in mid_files if not m.startswith("hope_models/")]
print("files naming mid_loop:", len(mid_files), "; in hope_models", len(mid_files) - len(outside), "; outside", len(outside))
print("function-local imports:", local_imports, "; of the project's own modules:", local_own)
