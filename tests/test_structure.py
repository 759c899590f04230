"""The code's structure (issue "One step, many terms"): layers whose imports only point down,
private names kept inside their module, classes and the step small enough to read."""
from __future__ import annotations

import ast
import collections
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("torchsph", "parallel")
EVERYWHERE = PACKAGES + ("scripts", "tests")


def _files(dirs):
    return [p for d in dirs for p in sorted((ROOT / d).rglob("*.py"))]  # subpackages (torchsph/terms) included


def _module(p: Path) -> str:
    parts = p.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_private_name_is_used_outside_its_own_module():
    """An attribute or module-level name with one leading underscore, defined in one of our
    modules, is read or written only there (by ``obj._x`` or ``from m import _x``)."""
    defined = collections.defaultdict(set)
    uses = []
    for p in _files(EVERYWHERE):
        tree = ast.parse(p.read_text())
        for n in ast.walk(tree):
            if isinstance(n, ast.Attribute) and _private(n.attr):
                if isinstance(n.value, ast.Name) and n.value.id in ("self", "cls"):
                    defined[n.attr].add(p)
                else:
                    uses.append((p, n.lineno, n.attr))
            elif isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and _private(n.name):
                defined[n.name].add(p)
            elif isinstance(n, ast.Assign):
                for t in n.targets:
                    for m in ast.walk(t):
                        if isinstance(m, ast.Name) and _private(m.id):
                            defined[m.id].add(p)
            elif isinstance(n, ast.ImportFrom) and n.module and n.module.split(".")[0] in PACKAGES + ("",):
                uses += [(p, n.lineno, a.name) for a in n.names if _private(a.name)]
            elif isinstance(n, ast.ImportFrom) and n.level:
                uses += [(p, n.lineno, a.name) for a in n.names if _private(a.name)]
    bad = [f"{p.relative_to(ROOT)}:{line} uses {name} (defined in "
           f"{', '.join(str(d.relative_to(ROOT)) for d in sorted(defined[name]))})"
           for p, line, name in uses if defined[name] and p not in defined[name]]
    assert not bad, "\n".join(bad)


def _import_graph() -> dict[str, set[str]]:
    files = {_module(p): p for p in _files(PACKAGES)}
    graph = {}
    for mod, p in files.items():
        pkg = mod if p.name == "__init__.py" else mod.rsplit(".", 1)[0]
        deps = set()
        for n in ast.walk(ast.parse(p.read_text())):  # function-level imports included
            if isinstance(n, ast.ImportFrom):
                if n.level:
                    base = pkg.split(".")[: len(pkg.split(".")) - (n.level - 1)]
                    target = ".".join(base + ([n.module] if n.module else []))
                else:
                    target = n.module or ""
                subs = {f"{target}.{a.name}" for a in n.names} & files.keys()
                deps |= subs if subs else ({target} & files.keys())
            elif isinstance(n, ast.Import):
                deps |= {a.name for a in n.names} & files.keys()
        deps.discard(mod)
        graph[mod] = deps
    return graph


def _cycles(graph):
    state, stack, found = {}, [], []

    def visit(u):
        state[u] = 1
        stack.append(u)
        for v in sorted(graph[u]):
            if state.get(v) == 1:
                found.append(stack[stack.index(v):] + [v])
            elif v not in state:
                visit(v)
        stack.pop()
        state[u] = 2

    for u in sorted(graph):
        if u not in state:
            visit(u)
    return found


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == [["a", "b", "c", "a"]]


def test_no_import_cycle_in_the_packages():
    """The import graph of torchsph/ and parallel/ (every import, at module or function level)
    has no cycle: the layers' imports only point down."""
    graph = _import_graph()
    assert "torchsph.scenes.builders" in graph and "torchsph.scenes.deposition" in graph["torchsph.scenes.builders"]
    assert _cycles(graph) == []
    # the solver never imports the MPI layer; the command line (torchsph.__main__) runs either
    core = {m: ds for m, ds in graph.items() if m.startswith("torchsph") and m != "torchsph.__main__"}
    assert not [(m, d) for m, ds in core.items() for d in ds if d.startswith("parallel")]


# the layers of torchsph/, lowest first: a module imports only from its own layer or those below
LAYERS = ("core", "physics", "step", "scenes", "io", "run", "post")


def _layer(mod: str) -> int | None:
    parts = mod.split(".")
    return LAYERS.index(parts[1]) if parts[0] == "torchsph" and len(parts) > 2 and parts[1] in LAYERS else None


def test_every_module_is_in_a_layer_and_imports_point_down():
    """torchsph/ is folders of layers (core, physics, step, scenes, io, run, post; the package's
    __init__ and __main__ above them): every import of a module, at module or function level,
    is of its own layer or one below. So the physics never imports the step, a scene, the I/O or
    the run loop, and nothing below the command line imports the MPI layer."""
    graph = _import_graph()
    loose = [m for m in graph if m.startswith("torchsph.") and _layer(m) is None
             and m not in ("torchsph.__main__",) and m.split(".")[1] not in LAYERS]
    assert loose == [], loose
    up = [f"{m} ({LAYERS[_layer(m)]}) imports {d} ({LAYERS[_layer(d)]})" for m, ds in graph.items()
          if _layer(m) is not None for d in ds if _layer(d) is not None and _layer(d) > _layer(m)]
    assert up == [], "\n".join(up)
    physics = [m for m in graph if _layer(m) == LAYERS.index("physics")]
    assert "torchsph.physics.thermal" in physics and "torchsph.physics.terms.heating" in physics
    assert not [(m, d) for m in physics for d in graph[m] if d.startswith(("parallel", "torchsph.step"))]


def test_the_direction_test_sees_an_upward_import():
    assert _layer("torchsph.step.rates") > _layer("torchsph.physics.fluid") > _layer("torchsph.core.state")
    assert _layer("torchsph.__main__") is None and _layer("torchsph.post.analysis") == len(LAYERS) - 1


def _sizes():
    for p in _files(PACKAGES):
        for n in ast.walk(ast.parse(p.read_text())):
            if isinstance(n, (ast.ClassDef, ast.FunctionDef)):
                yield p, n, n.end_lineno - n.lineno + 1


def test_no_class_over_300_lines_and_the_step_within_150():
    big = [f"{p.relative_to(ROOT)}: class {n.name} has {size} lines" for p, n, size in _sizes()
           if isinstance(n, ast.ClassDef) and size > 300]
    assert not big, "\n".join(big)
    step = [size for p, n, size in _sizes() if p.name == "simulation.py" and n.name == "advance"]
    assert step and step[0] <= 150, step
