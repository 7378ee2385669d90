"""The package's shape, read from the source with ast (nothing is imported): no import cycle
between clppm's modules, counting the imports inside functions; no private name (``_x``) taken
from another module; no import the graph cannot see; no function over 80 lines.

The layers (docs/architecture.md, :data:`LAYERS`): compute (OpenCL) -> scene -> output ->
integrators -> run -> analysis -> checks -> cli, with config, request, image and version at the
top level.  A module imports only from its own layer or below, so each can be read, tested and
replaced on its own.
"""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "clppm"
MAX_LINES = 80


def _modules() -> dict[str, Path]:
    mods = {}
    for p in sorted(PKG.rglob("*.py")):
        parts = list(p.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = p
    return mods


MODULES = _modules()
TREES = {m: ast.parse(p.read_text(encoding="utf-8"), str(p)) for m, p in MODULES.items()}


def _package(mod: str) -> str:
    return mod if MODULES[mod].name == "__init__.py" else mod.rsplit(".", 1)[0]


def _from(mod: str, node: ast.ImportFrom):
    """(target module, names taken from it, line) for one ``from X import ...`` in ``mod``."""
    if node.level:
        base = _package(mod).split(".")
        base = base[:len(base) - (node.level - 1)]
        src = ".".join(base + ([node.module] if node.module else []))
    else:
        src = node.module or ""
    if src not in MODULES:
        return
    for a in node.names:
        sub = f"{src}.{a.name}"
        yield (sub, [], node.lineno) if sub in MODULES else (src, [a.name], node.lineno)


def _imports(mod: str):
    """(target module, names taken from it, line) per import anywhere in ``mod`` (functions too)."""
    for n in ast.walk(TREES[mod]):
        if isinstance(n, ast.Import):
            for a in n.names:
                name = a.name
                while name and name not in MODULES:          # import clppm.x.y: the deepest module
                    name = name.rpartition(".")[0]
                if name:
                    yield name, [], n.lineno
        elif isinstance(n, ast.ImportFrom):
            yield from _from(mod, n)


def graph() -> dict[str, set[str]]:
    g = {m: set() for m in MODULES}
    for m in MODULES:
        for tgt, _, _ in _imports(m):
            if tgt != m:
                g[m].add(tgt)
    return g


def cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(g[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_the_graph_is_read():
    g = graph()
    assert len(MODULES) > 30
    assert "clppm.config" in g["clppm"]                      # a function-local import
    assert sum(len(v) for v in g.values()) > 100


def test_no_import_cycle():
    found = cycles(graph())
    assert found == [], "import cycles (counting imports inside functions): " + "; ".join(
        " <-> ".join(c) for c in found)


def test_no_private_name_from_another_module():
    bad = []
    for m in MODULES:
        modules_here = set()                 # names bound to a clppm module by an import
        for n in ast.walk(TREES[m]):
            if isinstance(n, ast.ImportFrom):
                for tgt, names, line in _from(m, n):
                    if tgt != m:
                        bad += [f"{MODULES[m].relative_to(ROOT)}:{line}: {x} from {tgt}"
                                for x in names if x.startswith("_") and not x.startswith("__")]
                    if not names:
                        modules_here.update(a.asname or a.name for a in n.names)
        for n in ast.walk(TREES[m]):
            if (isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)
                    and n.value.id in modules_here and n.attr.startswith("_")
                    and not n.attr.startswith("__")):
                bad.append(f"{MODULES[m].relative_to(ROOT)}:{n.lineno}: {n.value.id}.{n.attr}")
    assert bad == [], "private names used from another module: " + "; ".join(bad)


def test_no_hidden_import():
    """Every import is an import statement (what the graph above reads): no __import__, and
    importlib only for the package's lazy ``clppm.config`` / ``clppm.image`` (PEP 562) and in
    the API reference's generator, which imports the modules its table names (nothing imports
    it: ``python -m clppm.apiref``)."""
    bad = []
    for m in MODULES:
        for n in ast.walk(TREES[m]):
            if isinstance(n, ast.Call):
                f = n.func
                name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
                if name == "__import__" or (name == "import_module" and m not in ("clppm", "clppm.apiref")):
                    bad.append(f"{MODULES[m].relative_to(ROOT)}:{n.lineno}")
    assert bad == [], "imports the graph cannot see: " + ", ".join(bad)


def test_no_long_function():
    long = [f"{MODULES[m].relative_to(ROOT)}:{n.lineno} {n.name} ({n.end_lineno - n.lineno + 1} lines)"
            for m in MODULES for n in ast.walk(TREES[m])
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))
            and n.end_lineno - n.lineno + 1 > MAX_LINES]
    assert long == [], f"functions over {MAX_LINES} lines: " + "; ".join(long)


#: the layers, bottom up (the top-level modules config, request, image and version sit beside them)
LAYERS = ["compute", "scene", "output", "integrators", "run", "analysis", "checks", "cli"]


def _layer(mod: str) -> int | None:
    parts = mod.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else None


def test_no_layer_imports_from_above():
    up = [f"{m} -> {t}" for m, ts in graph().items() for t in ts
          if _layer(m) is not None and _layer(t) is not None and _layer(t) > _layer(m)]
    assert up == [], "imports from a layer above: " + "; ".join(sorted(up))
