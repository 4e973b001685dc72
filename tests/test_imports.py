"""Library code never imports the CLI toolkits (typer, rich); the package has no import cycles."""

from __future__ import annotations

import ast
import itertools
import subprocess
import sys
from pathlib import Path


def test_library_does_not_import_typer_or_rich():
    code = (
        "import sys\n"
        "import mutualslam_cli.pipeline, mutualslam_cli.report.tables, mutualslam_cli.stages.evaluation\n"
        "import mutualslam_cli.metrics.trajectory, mutualslam_cli.metrics.depth\n"
        "bad = sorted(m for m in ('typer', 'rich') if m in sys.modules)\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"library imported {out.stdout.strip()}"


# --------------------------------------------------------------------------- import graph

PACKAGE = "mutualslam_cli"
ROOT = Path(__file__).resolve().parents[1] / PACKAGE


def _module_names(root: Path = ROOT) -> dict[str, Path]:
    """Every module of the package: dotted name → file (a package is its ``__init__.py``)."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = (PACKAGE,) + path.relative_to(root).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Intra-package modules ``name`` imports anywhere in its file (module level, in functions,
    under ``TYPE_CHECKING``): ``from a import b`` counts as importing ``a.b`` when ``b`` is a
    module, else ``a``; relative imports are resolved against ``name``'s package."""
    is_pkg = path.name == "__init__.py"
    package = name.split(".") if is_pkg else name.split(".")[:-1]
    found: set[str] = set()

    def add(target: str) -> None:
        # `import a.b.c.d` where d is an attribute: the longest prefix that is a module
        while target and target not in modules:
            target = target.rpartition(".")[0]
        if target and target != name:
            found.add(target)

    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == PACKAGE or alias.name.startswith(PACKAGE + "."):
                    add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not (target == PACKAGE or target.startswith(PACKAGE + ".")):
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                add(sub if sub in modules else target)
    return found


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module → the intra-package modules it imports."""
    modules = _module_names(root)
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def import_cycles(graph: dict[str, set[str]]) -> list[tuple[list[str], list[str]]]:
    """Every strongly connected component of more than one module (Tarjan), each as
    ``(cycle, component)``: ``cycle`` is a shortest ``[a, b, …, a]`` through the component's
    first module, ``component`` all its modules, sorted; components in a stable order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    sccs: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                sccs.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    out = []
    for comp in sorted(sccs):
        members, start = set(comp), comp[0]
        prev: dict[str, str] = {start: start}
        frontier, last = [start], None
        while last is None:  # breadth first from start until an arrow leads back to it
            nxt = []
            for v in frontier:
                if start in graph[v]:
                    last = v
                    break
                for w in sorted(graph[v] & members):
                    if w not in prev:
                        prev[w] = v
                        nxt.append(w)
            frontier = nxt
        path = [last]
        while path[-1] != start:
            path.append(prev[path[-1]])
        out.append((path[::-1] + [start], comp))
    return out


def _describe(cycles: list[tuple[list[str], list[str]]]) -> str:
    lines = []
    for cycle, comp in cycles:
        lines.append(" → ".join(cycle))
        if len(comp) > len(cycle) - 1:
            lines.append(f"    (one tangle with: {', '.join(m for m in comp if m not in cycle)})")
    return "\n".join(lines)


def test_cycle_finder_on_a_known_graph():
    g = {"a": {"b"}, "b": {"c", "x"}, "c": {"a"}, "d": {"a", "e"}, "e": {"d", "b"}, "f": set(), "x": set()}
    assert import_cycles(g) == [(["a", "b", "c", "a"], ["a", "b", "c"]), (["d", "e", "d"], ["d", "e"])]
    g = {"a": {"b"}, "b": {"a", "c"}, "c": {"b"}}
    assert import_cycles(g) == [(["a", "b", "a"], ["a", "b", "c"])]
    assert "one tangle with: c" in _describe(import_cycles(g))
    assert import_cycles({"a": {"b"}, "b": set()}) == []


def test_import_graph_resolves_relative_and_submodule_imports(tmp_path: Path):
    pkg = tmp_path / PACKAGE
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "top.py").write_text("import os\n\ndef f():\n    from mutualslam_cli.sub import leaf\n")
    (pkg / "sub" / "__init__.py").write_text("from . import other\n")
    (pkg / "sub" / "leaf.py").write_text("from .other import X\nimport mutualslam_cli.top\n")
    (pkg / "sub" / "other.py").write_text(
        "from typing import TYPE_CHECKING\nfrom mutualslam_cli.sub import Y\n"
        "if TYPE_CHECKING:\n    from ..sub import leaf as _leaf\n")
    g = import_graph(pkg)
    P = PACKAGE
    assert g == {
        P: set(),
        f"{P}.top": {f"{P}.sub.leaf"},
        f"{P}.sub": {f"{P}.sub.other"},
        f"{P}.sub.leaf": {f"{P}.sub.other", f"{P}.top"},
        f"{P}.sub.other": {f"{P}.sub", f"{P}.sub.leaf"},
    }
    (cycle, comp), = import_cycles(g)
    assert cycle == [f"{P}.sub", f"{P}.sub.other", f"{P}.sub"]
    assert comp == [f"{P}.sub", f"{P}.sub.leaf", f"{P}.sub.other", f"{P}.top"]


def test_no_import_cycles():
    """Every import arrow inside the package points one way (a cycle couples its modules and
    breaks as soon as one of them imports the other at module level)."""
    cycles = import_cycles(import_graph())
    assert not cycles, "import cycles inside the package:\n" + _describe(cycles)


def test_no_import_cycles_between_subpackages():
    """Layers: collapsed to the package's top-level parts (``vo``, ``adapt``, ``evaluation``, …), the
    arrows still point one way, e.g. ``vo`` never imports a module that imports ``vo``."""
    def top(m: str) -> str:
        return ".".join(m.split(".")[:2])

    modules = import_graph()
    graph: dict[str, set[str]] = {}
    for m, deps in modules.items():
        graph.setdefault(top(m), set()).update(top(d) for d in deps if top(d) != top(m))
    cycles = import_cycles(graph)
    steps = {(a, b) for cycle, _ in cycles for a, b in itertools.pairwise(cycle)}
    arrows = sorted(f"{m} → {d}" for m, deps in modules.items() for d in deps if (top(m), top(d)) in steps)
    assert not cycles, ("import cycles between parts of the package:\n" + _describe(cycles)
                        + "\nmade of:\n" + "\n".join(arrows))


# --------------------------------------------------------------------------- layers

#: The house's floors: each part of the package (top-level module or subpackage) → its layer.
LAYER_OF = {
    "": "ground", "errors": "ground", "types": "ground", "config": "ground", "geometry": "ground", "pixels": "ground",
    "atomic": "ground", "allocator": "ground", "machine": "ground", "device": "ground",
    "map": "map", "datasets": "domain", "vo": "domain", "adapt": "domain", "metrics": "domain", "dense": "domain",
    "backend": "backend", "online": "online", "results": "results", "stages": "stages", "report": "report",
    "pipeline": "doors", "ablate": "doors", "grid_plan": "doors", "eval_depth": "doors", "bench": "bench",
    "book": "book", "cli": "cli",
}
#: What each layer may import (besides itself). The ground floor imports nothing above it; the map (keyframes,
#: points, frame records, their journal and their one writer) sits on it alone, under the domain; the domain
#: never imports the back end, stages, results, report, the front doors or the CLI; the back end (the map
#: after the front end: bridges, merges, loop closure, culling, BA) sits on the front end and the network
#: and writes no file and no summary key (the stages do); ``online`` (Algorithm 1 on one clock: the loop the
#: adaptation stage drives, its labels, realtime clock, online scores and Table 4's credit) drives the front end,
#: the network and the back end, and writes no file and no summary key either; results know the file formats
#: (datasets' TUM writer) and nothing that computes; the report reads results and files and re-applies the metrics'
#: formulas for its figures, never a stage or the VO / adaptation / BA; nothing imports the CLI but the CLI.
ALLOWED = {
    "ground": set(),
    "map": {"ground"},
    "domain": {"ground", "map"},
    "backend": {"ground", "map", "domain"},
    "results": {"ground", "datasets", "map"},
    "online": {"ground", "map", "domain", "backend"},
    "stages": {"ground", "map", "domain", "backend", "online", "results"},
    "report": {"ground", "results", "datasets", "metrics"},
    "doors": {"ground", "map", "domain", "backend", "online", "results", "stages"},
    "bench": {"ground", "map", "domain", "backend", "online", "results", "stages", "doors"},
    "book": {"ground", "map", "domain", "results", "report", "doors"},
    "cli": {"ground", "map", "domain", "backend", "online", "results", "stages", "report", "doors", "bench", "book"},
}


def _part(module: str) -> str:
    return module.split(".")[1] if "." in module else ""


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """Every import arrow the layer table forbids, as ``"a → b (layer → layer)"``; a part of the
    package missing from :data:`LAYER_OF` is a violation too (new parts must be placed)."""
    out = []
    for m, deps in sorted(graph.items()):
        src = LAYER_OF.get(_part(m))
        if src is None:
            out.append(f"{m}: part {_part(m)!r} has no layer in LAYER_OF")
            continue
        for d in sorted(deps):
            dst = LAYER_OF.get(_part(d))
            ok = dst is not None and (dst == src or dst in ALLOWED[src] or _part(d) in ALLOWED[src])
            if not ok:
                out.append(f"{m} → {d} ({src} → {dst})")
    return out


def test_layers_hold():
    """The house keeps its shape: no import runs against the layer table."""
    bad = layer_violations(import_graph())
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


#: The floors inside ``datasets`` (its top-level modules and sub-packages → floor): the file formats every
#: run reads at the bottom; the user's recordings and the rendered rooms above them, each on its own; the
#: registry and the check (a name, folder or recording → a Sequence) above those; the download on top.
DATASETS_FLOOR_OF = {
    "sequence": "formats", "associate": "formats", "layout": "formats", "image_files": "formats",
    "fy_sign": "formats", "tum": "formats", "icl_nuim": "formats", "predictions": "formats", "splice": "formats",
    "recordings": "recordings", "synthetic": "synthetic",
    "": "registry", "registry": "registry", "check": "registry",
    "download": "download",
}
#: What each floor inside ``datasets`` may import (besides its own floor): a recording is written with the
#: TUM writers and read back like any folder; the registry opens recordings; a download reads the registry
#: and runs the check; nothing imports the download or the rendered rooms from inside ``datasets``.
DATASETS_ALLOWED = {
    "formats": set(),
    "recordings": {"formats"},
    "synthetic": {"formats"},
    "registry": {"formats", "recordings"},
    "download": {"formats", "registry"},
}


def _datasets_part(module: str) -> str:
    parts = module.split(".")
    return parts[2] if len(parts) > 2 else ""


def datasets_floor_violations(graph: dict[str, set[str]]) -> list[str]:
    """Every import arrow between two modules of ``datasets`` that :data:`DATASETS_ALLOWED` forbids; a
    module or sub-package of ``datasets`` missing from :data:`DATASETS_FLOOR_OF` is a violation too."""
    out = []
    inside = {m: deps for m, deps in graph.items() if _part(m) == "datasets"}
    for m, deps in sorted(inside.items()):
        src = DATASETS_FLOOR_OF.get(_datasets_part(m))
        if src is None:
            out.append(f"{m}: {_datasets_part(m)!r} has no floor in DATASETS_FLOOR_OF")
            continue
        for d in sorted(x for x in deps if _part(x) == "datasets"):
            dst = DATASETS_FLOOR_OF.get(_datasets_part(d))
            if not (dst == src or dst in DATASETS_ALLOWED[src]):
                out.append(f"{m} → {d} ({src} → {dst})")
    return out


def test_datasets_floors_hold():
    """Inside ``datasets`` the arrows point one way: formats ← recordings, synthetic ← registry ← download."""
    bad = datasets_floor_violations(import_graph())
    assert not bad, "imports against the floors of datasets:\n" + "\n".join(bad)


def test_a_planted_import_against_the_datasets_floors_is_caught(tmp_path: Path):
    pkg = tmp_path / PACKAGE
    for rel, text in {
        "__init__.py": "", "datasets/__init__.py": "from mutualslam_cli.datasets.registry import load\n",
        "datasets/associate.py": "", "datasets/registry.py": "from mutualslam_cli.datasets.download import entry\n",
        "datasets/download/__init__.py": "",
        "datasets/download/entry.py": "from mutualslam_cli.datasets import registry\n",
        "datasets/recordings/__init__.py": "",
        "datasets/recordings/video.py": "from mutualslam_cli.datasets.synthetic.scenes import x\n",
        "datasets/synthetic/__init__.py": "", "datasets/synthetic/scenes.py": "from ..associate import y\n",
        "datasets/newfile.py": "",
    }.items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(text)
    D = f"{PACKAGE}.datasets"
    assert datasets_floor_violations(import_graph(pkg)) == [
        f"{D}.newfile: 'newfile' has no floor in DATASETS_FLOOR_OF",
        f"{D}.recordings.video → {D}.synthetic.scenes (recordings → synthetic)",
        f"{D}.registry → {D}.download.entry (registry → download)",
    ]


def test_a_planted_forbidden_import_is_caught(tmp_path: Path):
    """A domain module importing a stage, a report module importing the VO, the ground floor importing
    the domain, and anything importing the CLI: each is named."""
    pkg = tmp_path / PACKAGE
    for rel, text in {
        "__init__.py": "", "errors.py": "", "geometry.py": "from mutualslam_cli.vo import frontend\n",
        "vo/__init__.py": "", "vo/frontend.py": "from mutualslam_cli.stages import ba\n",
        "stages/__init__.py": "", "stages/ba.py": "from mutualslam_cli.vo import frontend\n",
        "report/__init__.py": "", "report/plots.py": "from mutualslam_cli.vo.frontend import run_vo\n",
        "metrics/__init__.py": "", "metrics/depth.py": "def f():\n    from mutualslam_cli.cli import app\n",
        "cli/__init__.py": "", "newpart.py": "",
    }.items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(text)
    bad = layer_violations(import_graph(pkg))
    P = PACKAGE
    assert bad == [
        f"{P}.geometry → {P}.vo.frontend (ground → domain)",
        f"{P}.metrics.depth → {P}.cli (domain → cli)",
        f"{P}.newpart: part 'newpart' has no layer in LAYER_OF",
        f"{P}.report.plots → {P}.vo.frontend (report → domain)",
        f"{P}.vo.frontend → {P}.stages.ba (domain → stages)",
    ]


def test_a_planted_import_against_the_back_end_is_caught(tmp_path: Path):
    """The back end sits on the front end and the network: the front end importing it, or the back end importing
    a stage or results (it writes no file and no summary key), is named; a stage importing it is not."""
    pkg = tmp_path / PACKAGE
    for rel, text in {
        "__init__.py": "", "vo/__init__.py": "", "vo/feedback.py": "from mutualslam_cli.backend import refine\n",
        "backend/__init__.py": "", "backend/refine.py": "from mutualslam_cli.vo import feedback\n",
        "backend/loop_closer.py": "from mutualslam_cli.results.summary import Summary\n",
        "results/__init__.py": "", "results/summary.py": "",
        "stages/__init__.py": "", "stages/ba.py": "from mutualslam_cli.backend.refine import MapBA\n",
    }.items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(text)
    P = PACKAGE
    assert layer_violations(import_graph(pkg)) == [
        f"{P}.backend.loop_closer → {P}.results.summary (backend → results)",
        f"{P}.vo.feedback → {P}.backend.refine (domain → backend)",
    ]
