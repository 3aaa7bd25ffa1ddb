"""Import cycles and the package layering of conecal (issue 31).

Reads every module's imports with ``ast`` (module-level and function-level
alike: a lazy import is still a dependency), resolves relative imports, and
prints (1) cycles between modules (strongly connected components), not
counting a package's ``__init__`` re-exporting its own submodules,
(2) the graph between the top-level packages, with its cycles, and (3) the
imports that go up the declared layering ``LAYERS`` (a package may import
only from layers below its own; a package missing from ``LAYERS`` counts as
a failure too, so a new package must be placed).

    python benchmarks/import_graph.py
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# bottom to top; each row may import from the rows above it in this list only
LAYERS = [
    ["errors", "stats", "jit"],               # plain values, numbers, compiled loops
    ["binding", "geometry"],                  # documents' base model; projection geometry
    ["kinematics"],                           # chains of geometry
    ["scan"],                                 # the scan contract (YAML, frames)
    ["documents"],                            # output documents' models
    ["jsonio"],                               # reading and writing them
    ["parts"],                                # sharded outputs
    ["effects", "fit"],                       # effect physics; the least-squares core and fits
    ["calib", "detect", "consistency", "simulate", "export"],   # stages
    ["diagnose", "report"],                   # analysis over stages (diagnose simulates; report exports)
    ["cli"],                                  # thin commands
]


def modules() -> dict[str, Path]:
    out = {}
    for p in (ROOT / "conecal").rglob("*.py"):
        name = ".".join(p.relative_to(ROOT).with_suffix("").parts)
        out[name.removesuffix(".__init__")] = p
    return out


def graph(mods: dict[str, Path]) -> dict[str, set[str]]:
    g = {m: set() for m in mods}
    for m, p in mods.items():
        pkg = m if p.name == "__init__.py" else m.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    parts = pkg.split(".")
                    base = ".".join(parts[:len(parts) - (node.level - 1)])
                    tgt = base + (f".{node.module}" if node.module else "")
                else:
                    tgt = node.module or ""
                if not tgt.startswith("conecal"):
                    continue
                subs = [f"{tgt}.{a.name}" for a in node.names if f"{tgt}.{a.name}" in mods]
                deps = subs if subs and len(subs) == len(node.names) else [tgt] + subs
                g[m].update(d for d in deps if d in mods and d != m)
            elif isinstance(node, ast.Import):
                g[m].update(a.name for a in node.names if a.name in mods and a.name != m)
    return g


def cycles(g: dict[str, set[str]]) -> list[list[str]]:
    index, low, stack, on, out, n = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = n[0]
        n[0] += 1
        stack.append(v)
        on.add(v)
        for w in g[v]:
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

    sys.setrecursionlimit(10000)
    for v in g:
        if v not in index:
            visit(v)
    return out


def main() -> int:
    mods = modules()
    g = graph(mods)
    # a package's __init__ importing its submodules, which import siblings: a re-export, not a cycle
    g_no_init = {m: {d for d in deps if not (mods[d].name == "__init__.py" and m.startswith(d + "."))}
                 for m, deps in g.items()}
    mc = cycles(g_no_init)
    print(f"module cycles: {len(mc)}")
    for c in mc:
        print("  " + " <-> ".join(c))
    top = lambda m: ".".join(m.split(".")[:2])   # noqa: E731
    pg = {}
    for m, deps in g.items():
        for d in deps:
            if top(m) != top(d) and top(d) != "conecal":
                pg.setdefault(top(m), set()).add(top(d))
    pc = cycles({k: pg.get(k, set()) for k in {top(m) for m in mods}})
    print(f"package cycles: {len(pc)}")
    for c in pc:
        print("  " + " <-> ".join(c))
    for k in sorted(pg):
        print(f"  {k} -> {', '.join(sorted(pg[k]))}")
    layer = {f"conecal.{p}": i for i, row in enumerate(LAYERS) for p in row}
    up = [(a, b) for a in sorted(pg) for b in sorted(pg[a])
          if a not in layer or b not in layer or layer[b] >= layer[a]]
    print(f"imports up or across the layering: {len(up)}")
    for a, b in up:
        print(f"  {a} -> {b}")
    return 1 if mc or pc or up else 0


if __name__ == "__main__":
    sys.exit(main())
