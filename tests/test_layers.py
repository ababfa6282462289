"""Imports go one way: the layer order drawn at the top of docs/architecture.md, checked here.

Every module of the project's packages is parsed (ast, not imported), and every import in it is
checked: at module level or inside a function, `import a.b`, `from a.b import c`, `from . import c`
and `from ..a import b` alike, and the modules a file imports by name at run time
(`importlib.import_module` over a table of names: the CLI's COMMANDS, the webapp's BLUEPRINTS,
the components' table). No module may import itself through others (a cycle of modules, however
the imports hide: inside functions or by name).

    hope_models < registry < daemon, workers (neither imports the other) < webapp < hope_trainer < run_trainer.py

Inside hope_models, HOPE_MODELS_TIERS from the bottom up; a sub-package may import its own tier
and the tiers below it, never one above, and no two sub-packages may import each other. The
single-file modules directly in hope_models/ (settings, paths, durable, json_finite, ...) are
the foundation under every tier: they import nothing of hope_models but each other.

bench/ and tests/ stand outside the rule: they may reach into any layer.
"""
from __future__ import annotations

import ast
import functools
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

# What each top-level layer may import besides itself. migrations/ is the registry's Alembic
# scripts (registry/db.py runs them, migrations/env.py reads the registry's tables): one layer.
LAYERS: dict[str, frozenset[str]] = {
    "hope_models": frozenset(),
    "registry": frozenset({"hope_models", "migrations"}),
    "migrations": frozenset({"hope_models", "registry"}),
    "daemon": frozenset({"hope_models", "registry", "migrations"}),
    "workers": frozenset({"hope_models", "registry", "migrations"}),
    "webapp": frozenset({"hope_models", "registry", "migrations", "daemon", "workers"}),
    "hope_trainer": frozenset({"hope_models", "registry", "migrations", "daemon", "workers", "webapp"}),
    "run_trainer": frozenset({"hope_models", "registry", "migrations", "daemon", "workers", "webapp",
                              "hope_trainer"}),
}
ORDER_TEXT = ("hope_models < registry (+ migrations) < daemon, workers (neither imports the other) < webapp "
              "< hope_trainer < run_trainer.py")

# hope_models' sub-packages, bottom tier first; a tier's members are peers (one may import the
# other, never both ways).
HOPE_MODELS_TIERS: tuple[tuple[str, ...], ...] = (
    ("rlds", "media"),
    ("data", "sim"),
    ("components",),
    ("train", "intake"),
    ("promote", "runtime", "imagine"),
    ("cli",),
)

# The packages whose own processes must never load torch (the daemon, the webapp and a worker's
# parent: torch costs hundreds of MB on a Pi); training imports it only inside the job's child,
# through hope_models.
NO_TORCH = ("daemon", "registry", "webapp", "workers")


@dataclass(frozen=True)
class Import:
    file: str  # relative to the repo
    line: int
    module: str  # the absolute dotted name imported

    def where(self) -> str:
        return f"{self.file}:{self.line}"


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _resolve(path: Path, node: ast.ImportFrom, root: Path) -> str:
    """The absolute module a relative `from` import names (level 1 is the module's package)."""
    package = _module_name(path, root).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    if node.level > len(package):
        raise AssertionError(f"{path.relative_to(root)}:{node.lineno}: relative import beyond the top package")
    base = package[:len(package) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(path: Path, root: Path = REPO) -> list[Import]:
    """Every import in the file, anywhere in it. `from a import b` yields a.b when a.b is a
    module of the project (so `from hope_models import cli` names the sub-package), else a."""
    rel = str(path.relative_to(root))
    found: list[Import] = []
    for node in ast.walk(ast.parse(path.read_text(), filename=rel)):
        if isinstance(node, ast.Import):
            found += [Import(rel, node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(path, node, root) if node.level else (node.module or "")
            for alias in node.names:
                sub = f"{base}.{alias.name}" if base else alias.name
                found.append(Import(rel, node.lineno, sub if _is_project_module(sub, root) else base))
    found += by_name_imports(path, root)
    return list(dict.fromkeys(found))  # `from a import b, c` of two names: one import of a


def _docstrings(tree: ast.AST) -> set[int]:
    return {id(node.body[0].value) for node in ast.walk(tree)
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body
            and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}


def by_name_imports(path: Path, root: Path = REPO) -> list[Import]:
    """The project modules a file imports by name at run time: for each `import_module(x)` call,
    x a string naming a project module, or an f-string whose constant prefix (`__name__` counts as
    the file's own module) completes to one with a string constant of the file, or a variable, when
    the file's string constants name project modules. A prefix that is not constant
    (`f"{self.package}.{part}"`) cannot be read here."""
    rel = str(path.relative_to(root))
    tree = ast.parse(path.read_text(), filename=rel)
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and n.args and (
        (isinstance(n.func, ast.Name) and n.func.id == "import_module")
        or (isinstance(n.func, ast.Attribute) and n.func.attr == "import_module"))]
    if not calls:
        return []
    skip = _docstrings(tree) | {id(v) for n in ast.walk(tree) if isinstance(n, ast.JoinedStr) for v in n.values}
    strings = [n.value for n in ast.walk(tree)
               if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in skip]
    own = _module_name(path, root)
    found = []
    for call in calls:
        arg = call.args[0]
        if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
            names = [arg.value]
        elif isinstance(arg, ast.JoinedStr):
            prefix = ""
            for part in arg.values[:-1]:
                if isinstance(part, ast.Constant):
                    prefix += str(part.value)
                elif isinstance(part, ast.FormattedValue) and isinstance(part.value, ast.Name) \
                        and part.value.id == "__name__":
                    prefix += own
                else:
                    prefix = None
                    break
            names = [prefix + s for s in strings] if prefix else []
        else:
            names = strings
        found += [Import(rel, call.lineno, n) for n in names
                  if all(part.isidentifier() for part in n.split(".")) and _is_project_module(n, root)]
    return found


def _is_project_module(dotted: str, root: Path) -> bool:
    path = root.joinpath(*dotted.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def project_files() -> list[Path]:
    files = [REPO / "run_trainer.py"]
    for top in LAYERS:
        if (REPO / top).is_dir():
            files += sorted(p for p in (REPO / top).rglob("*.py") if "node_modules" not in p.parts)
    return files


def layer_of(module: str) -> str | None:
    top = module.split(".")[0]
    return top if top in LAYERS else None


def _sub_of(module: str) -> str:
    """hope_models' sub-package (or foundation module) a hope_models module belongs to."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _tier(sub: str, root: Path = REPO) -> int | None:
    """-1 for a foundation module (a single file in hope_models/), the tier of a sub-package, or
    None for a sub-package HOPE_MODELS_TIERS does not place."""
    if sub == "__init__" or (root / "hope_models" / f"{sub}.py").is_file():
        return -1
    for i, tier in enumerate(HOPE_MODELS_TIERS):
        if sub in tier:
            return i
    return None


@functools.lru_cache(maxsize=1)
def _all_imports() -> tuple[Import, ...]:
    return tuple(imp for path in project_files() for imp in imports_of(path))


def all_imports() -> list[Import]:
    """Every import of the checkout's files: parsed once per test process (the files do not change during it)."""
    return list(_all_imports())


def layer_violations(imports: list[Import], root: Path = REPO) -> list[str]:
    bad = []
    for imp in imports:
        src, dst = layer_of(_module_name(root / imp.file, root)), layer_of(imp.module)
        if dst is None or dst == src:
            continue
        if dst not in LAYERS[src]:
            bad.append(f"{imp.where()}: {src} imports {imp.module} ({dst}); the layers are {ORDER_TEXT}")
    return bad


def hope_models_edges(imports: list[Import], root: Path = REPO) -> list[tuple[Import, str, str]]:
    """(import, from sub-package, to sub-package) for imports between hope_models' parts."""
    edges = []
    for imp in imports:
        if not imp.file.startswith("hope_models/") or layer_of(imp.module) != "hope_models":
            continue
        src, dst = _sub_of(_module_name(root / imp.file, root)), _sub_of(imp.module)
        if src != dst:
            edges.append((imp, src, dst))
    return edges


def _problem(imp: Import, src: str, dst: str, pairs: set[tuple[str, str]], root: Path) -> str | None:
    """What is wrong with one import between hope_models' parts (None: nothing), given `pairs`,
    the (importer, imported) parts of the imports that count."""
    t_src, t_dst = _tier(src, root), _tier(dst, root)
    if t_src is None or t_dst is None:
        return None  # test_every_hope_models_part_is_placed says so
    if t_src == -1 and t_dst != -1:
        return (f"{imp.where()}: the foundation module hope_models/{src}.py imports {imp.module}; "
                "foundation modules import nothing of hope_models but each other")
    if t_dst > t_src:
        tiers_text = " < ".join("/".join(t) for t in HOPE_MODELS_TIERS)
        return (f"{imp.where()}: hope_models.{src} imports {imp.module}, a higher tier; "
                f"inside hope_models: foundation < {tiers_text}")
    if (dst, src) in pairs:
        return (f"{imp.where()}: hope_models.{src} imports {imp.module} while hope_models.{dst} imports "
                f"hope_models.{src}: two parts of hope_models must not import each other")
    return None


def hope_models_violations(edges: list[tuple[Import, str, str]], root: Path = REPO) -> list[str]:
    pairs = {(a, b) for _, a, b in edges}
    return [p for p in (_problem(*e, pairs, root) for e in edges) if p is not None]


def torch_imports(imports: list[Import]) -> list[str]:
    return [f"{imp.where()}: imports {imp.module}; {imp.file.split('/')[0]}/ never loads torch (only a job's "
            "child does, through hope_models)" for imp in imports
            if imp.file.split("/")[0] in NO_TORCH and imp.module.split(".")[0] == "torch"]


def test_layers_import_downwards_only():
    bad = layer_violations(all_imports())
    assert not bad, "imports against the layer order:\n" + "\n".join(bad)


def test_hope_models_parts_import_downwards_only():
    bad = hope_models_violations(hope_models_edges(all_imports()))
    assert not bad, "imports against hope_models' order:\n" + "\n".join(bad)


def test_no_torch_in_the_service_packages():
    bad = torch_imports(all_imports())
    assert not bad, "\n".join(bad)


def module_cycles(imports: list[Import], root: Path = REPO) -> list[list[str]]:
    """The cycles of the project's module graph (its strongly connected parts of two or more
    modules), each sorted."""
    graph: dict[str, set[str]] = {}
    for imp in imports:
        src = _module_name(root / imp.file, root)
        if imp.module != src and layer_of(imp.module) is not None and _is_project_module(imp.module, root):
            graph.setdefault(src, set()).add(imp.module)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []
    for start in sorted(graph):  # Tarjan's algorithm, iterative: the graph is a few hundred modules
        if start in index:
            continue
        work = [(start, iter(sorted(graph.get(start, ()))))]
        index[start] = low[start] = len(index)
        stack.append(start)
        while work:
            node, edges = work[-1]
            nxt = next(edges, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    work.append((nxt, iter(sorted(graph.get(nxt, ())))))
                elif nxt in stack:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                part = []
                while True:
                    member = stack.pop()
                    part.append(member)
                    if member == node:
                        break
                if len(part) > 1:
                    cycles.append(sorted(part))
    return cycles


def test_no_module_imports_itself_through_others():
    cycles = module_cycles(all_imports())
    assert not cycles, ("modules that import each other (move what both need below them):\n"
                        + "\n".join(" <-> ".join(c) for c in cycles))


def test_the_registries_by_name_are_read():
    seen = {(i.file, i.module) for i in all_imports()}
    for file, module in (("hope_trainer/cli.py", "hope_models.cli.train"), ("hope_trainer/cli.py", "daemon.cli.daemon"),
                         ("webapp/api/__init__.py", "webapp.api.health"),
                         ("hope_models/components/__init__.py", "hope_models.components.mid_loop")):
        assert (file, module) in seen, (file, module)


def test_every_hope_models_part_is_placed():
    subs = {p.name for p in (REPO / "hope_models").iterdir() if (p / "__init__.py").is_file()}
    unplaced = sorted(sub for sub in subs if _tier(sub) is None)
    assert not unplaced, (f"hope_models sub-packages in no tier: {unplaced}; place them in HOPE_MODELS_TIERS "
                          "(tests/test_layers.py) and in the drawing in docs/architecture.md")


# -- the checker itself, on made-up files ---------------------------------------------------------

def _fake(tmp_path: Path, rel: str, text: str) -> Path:
    path = tmp_path / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_the_checker_sees_every_import_form(tmp_path):
    for rel in ("hope_models/__init__.py", "hope_models/settings.py", "hope_models/data/__init__.py",
                "hope_models/data/cache.py", "hope_models/train/__init__.py", "hope_models/train/loop.py",
                "hope_models/cli/__init__.py", "workers/__init__.py", "daemon/__init__.py"):
        _fake(tmp_path, rel, "")
    path = _fake(tmp_path, "hope_models/data/x.py", (
        "import json\n"
        "from . import cache\n"
        "from ..train import loop\n"
        "from .. import settings\n"
        "def f():\n"
        "    import hope_models.cli\n"
        "    from hope_models import cli\n"
        "    import daemon\n"))
    imports = imports_of(path, tmp_path)
    assert [(i.line, i.module) for i in imports] == [
        (1, "json"), (2, "hope_models.data.cache"), (3, "hope_models.train.loop"), (4, "hope_models.settings"),
        (6, "hope_models.cli"), (7, "hope_models.cli"), (8, "daemon")]
    assert [b.split(":")[1] for b in layer_violations(imports, tmp_path)] == ["8"]
    bad = hope_models_violations(hope_models_edges(imports, tmp_path), tmp_path)
    assert [b.split(":")[1] for b in bad] == ["3", "6", "7"] and all("higher tier" in b for b in bad)

    sideways = _fake(tmp_path, "workers/y.py", "from daemon import z\n")
    assert "workers imports daemon" in layer_violations(imports_of(sideways, tmp_path), tmp_path)[0]
    found = _fake(tmp_path, "hope_models/settings.py", "from hope_models.data import cache\n")
    assert "foundation module" in hope_models_violations(hope_models_edges(imports_of(found, tmp_path), tmp_path),
                                                         tmp_path)[0]
    _fake(tmp_path, "hope_models/sim/__init__.py", "from hope_models.data import cache\n")
    mutual = imports_of(tmp_path / "hope_models/sim/__init__.py", tmp_path) + imports_of(
        _fake(tmp_path, "hope_models/data/z.py", "import hope_models.sim\n"), tmp_path)
    bad = hope_models_violations(hope_models_edges(mutual, tmp_path), tmp_path)
    assert len(bad) == 2 and all("must not import each other" in b for b in bad)
    ok = imports_of(tmp_path / "hope_models/sim/__init__.py", tmp_path)  # one way only: fine
    assert hope_models_violations(hope_models_edges(ok, tmp_path), tmp_path) == []
    local = _fake(tmp_path, "webapp/x.py", "def f():\n    import torch.nn\n")
    assert "webapp/ never loads torch" in torch_imports(imports_of(local, tmp_path))[0]


def test_the_checker_reads_imports_by_name_and_finds_cycles(tmp_path):
    for rel in ("webapp/__init__.py", "webapp/api/__init__.py", "webapp/api/health.py", "webapp/api/runs.py",
                "daemon/__init__.py", "daemon/cli.py", "registry/__init__.py"):
        _fake(tmp_path, rel, "")
    table = _fake(tmp_path, "registry/table.py", (
        "import importlib\n"
        "NAMES = ('health', 'runs', 'nothing')\n"
        "COMMANDS = {'x': 'daemon.cli'}\n"
        "def load(name, dotted):\n"
        "    importlib.import_module(f'webapp.api.{name}')\n"
        "    importlib.import_module(f'{__name__}.{name}')\n"
        "    return importlib.import_module(dotted)\n"))
    got = sorted({(i.line, i.module) for i in by_name_imports(table, tmp_path)})
    assert got == [(5, "webapp.api.health"), (5, "webapp.api.runs"), (7, "daemon.cli")]
    bad = layer_violations(imports_of(table, tmp_path), tmp_path)
    assert len(bad) == 3 and any("registry imports daemon.cli" in b for b in bad), bad
    a = _fake(tmp_path, "webapp/a.py", "def f():\n    from webapp import b\n")
    b = _fake(tmp_path, "webapp/b.py", "import webapp.c\n")
    c = _fake(tmp_path, "webapp/c.py", "import importlib\nimportlib.import_module('webapp.a')\n")
    cycle = imports_of(a, tmp_path) + imports_of(b, tmp_path) + imports_of(c, tmp_path)
    assert module_cycles(cycle, tmp_path) == [["webapp.a", "webapp.b", "webapp.c"]]
    assert module_cycles(imports_of(a, tmp_path) + imports_of(b, tmp_path), tmp_path) == []
