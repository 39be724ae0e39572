"""The package's shape: data flows one way through the stages, no import cycles, no private names
imported across modules, no module too large to read. Parsed with ``ast``, nothing imported."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# Modules under everything: any stage may import them; they import only each other.
FOUNDATION = {"version", "validation", "files", "graphs", "interop", "distributed", "state", "dynamics"}
# The pipeline stages, lowest first: a stage imports foundation modules, itself and lower stages.
STAGES = ["sim", "data", "gn", "models", "eval", "train", "control", "rl", "demo", "cli", "__main__"]
MAX_LINES = 700


def _modules() -> dict[str, Path]:
    mods = {}
    for top, prefix in (("gnwarp", "gnwarp"), ("kernels", "gnwarp.kernels")):
        for p in sorted((ROOT / top).rglob("*.py")):
            if top == "gnwarp" and "kernels" in p.relative_to(ROOT / top).parts:
                continue  # a source checkout may link gnwarp/kernels -> ../kernels
            rel = p.relative_to(ROOT / top).with_suffix("").parts
            name = ".".join((prefix,) + rel)
            mods[name.removesuffix(".__init__")] = p
    return mods


MODULES = _modules()


def _resolve(name: str) -> str | None:
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _imports(mod: str, path: Path) -> list[tuple[str, str | None]]:
    """(imported module, imported name or None) for every import in the file, lazy ones too."""
    tree = ast.parse(path.read_text())
    pkg = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = pkg.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            for a in node.names:
                full = f"{base}.{a.name}"
                out.append((full if full in MODULES else base, a.name))
        elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str)
              and getattr(node.func, "id", getattr(node.func, "attr", "")) in ("__import__", "import_module")):
            out.append((node.args[0].value, None))  # __import__("gnwarp") hides an import from ast
    return [(t, n) for t, n in out if t.startswith("gnwarp")]


def _layer(mod: str) -> tuple[str, int]:
    """('foundation', -1), ('kernels', stage index) or ('stage', stage index) of a module."""
    parts = mod.split(".")
    if parts[1] == "kernels":
        sub = parts[2] if len(parts) > 2 else ""
        return ("kernels", STAGES.index(sub) if sub in STAGES else -1)
    if parts[1] in FOUNDATION:
        return ("foundation", -1)
    assert parts[1] in STAGES, f"{mod}: not in a known stage; add it to FOUNDATION or STAGES"
    return ("stage", STAGES.index(parts[1]))


def _edges():
    for mod, path in MODULES.items():
        for target, name in _imports(mod, path):
            r = _resolve(target)
            if r and r != mod:
                yield mod, r, name


def test_every_module_sits_in_a_layer():
    for mod in MODULES:
        if mod != "gnwarp":
            _layer(mod)


def test_no_imports_up_the_layers():
    ups = []
    for mod, target, _ in _edges():
        if mod == "gnwarp" or target == "gnwarp.version":
            continue  # the package's public API re-exports every stage
        if target == "gnwarp":
            ups.append(f"{mod} imports the package root (import from the module that defines the name)")
            continue
        kind, level = _layer(mod)
        tkind, tlevel = _layer(target)
        if kind == "kernels":
            if tkind != "kernels":
                ups.append(f"{mod} (a kernel module) imports {target}")
        elif tkind == "kernels":
            if tlevel > level:
                ups.append(f"{mod} imports the kernels of a higher stage, {target}")
        elif kind == "foundation":
            if tkind != "foundation":
                ups.append(f"{mod} (foundation) imports the stage module {target}")
        elif tkind == "stage" and tlevel > level:
            ups.append(f"{mod} imports {target}, a higher stage")
    assert not ups, "imports up the layers:\n" + "\n".join(sorted(set(ups)))


def test_no_private_names_across_modules():
    bad = sorted({f"{m} <- {t}.{n}" for m, t, n in _edges()
                  if n and n.startswith("_") and not n.startswith("__")})
    assert not bad, "private names imported across modules:\n" + "\n".join(bad)


def test_no_import_cycles():
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for m, t, _ in _edges():
        if m != "gnwarp" and t != "gnwarp":
            graph[m].add(t)
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(v, stack):
        state[v] = 1
        stack.append(v)
        for w in sorted(graph[v]):
            if state.get(w) == 1:
                cycle.extend(stack[stack.index(w):] + [w])
                return True
            if w not in state and visit(w, stack):
                return True
        stack.pop()
        state[v] = 2
        return False

    for v in sorted(graph):
        if v not in state and visit(v, []):
            break
    assert not cycle, "import cycle: " + " -> ".join(cycle)


@pytest.mark.parametrize("mod", sorted(m for m in MODULES if not m.startswith("gnwarp.kernels")))
def test_module_size(mod):
    n = len(MODULES[mod].read_text().splitlines())
    assert n <= MAX_LINES, f"{MODULES[mod].relative_to(ROOT)} has {n} lines (> {MAX_LINES}): split it by job"


def test_bench_never_imports_the_cli():
    bad = []
    for p in sorted((ROOT / "bench").rglob("*.py")):
        for node in ast.walk(ast.parse(p.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            names += [f"{node.module}.{a.name}" for a in node.names] if isinstance(node, ast.ImportFrom) else []
            if any(n == "gnwarp.cli" or n.startswith("gnwarp.cli.") for n in names):
                bad.append(str(p.relative_to(ROOT)))
    assert not bad, "bench scripts import the command line (import the library instead): " + ", ".join(sorted(set(bad)))
