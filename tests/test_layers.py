"""The package's layering: no import circles between modules (imports inside functions included),
and the torch losses importable without Warp."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "simgen"


def module_graph() -> dict[str, set[str]]:
    """Module -> the simgen modules it imports anywhere in its source (a package counts as its
    __init__). A module's imports of its own parent packages and a package's imports of its own
    submodules are left out: Python runs those as part of importing the package itself."""
    files = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                candidates = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                candidates = [f"{base}.{a.name}" for a in node.names] + [base]
            else:
                continue
            for target in candidates:
                while target and target not in files:
                    target = target.rpartition(".")[0]
                if target and target != name and not name.startswith(target + ".") \
                        and not target.startswith(name + "."):
                    targets.add(target)
                    break
        graph[name] = targets
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` (a list of modules, the first repeated at the end), or None."""
    state, stack = {}, []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_the_module_graph_has_no_circles():
    graph = module_graph()
    # Module-level and function-level imports are both edges.
    assert "simgen.dataset.execute" in graph["simgen.dataset.generate"]
    assert "simgen.dataset.distributed" in graph["simgen.dataset.generate"]
    cycle = find_cycle(graph)
    assert cycle is None, "import circle: " + " -> ".join(cycle)


def test_find_cycle_finds_a_planted_circle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_the_torch_losses_import_without_warp():
    # Importing the losses, building a garment's rest data (materials, hinges) and reading a dataset
    # spec into solver settings stay Warp-free.
    code = ("import sys, numpy as np, simgen.physics\n"
            "v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.1]], float)\n"
            "simgen.physics.ClothRest.from_mesh(v, np.array([[0, 1, 2], [1, 3, 2]]))\n"
            "from simgen.dataset.spec import load_spec\n"
            "load_spec('thesis-tshirt').solver_options()\n"
            "print('warp' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_the_readme_layout_matches_the_tree():
    """Every path the README's layout names exists, and every public module, package and top-level
    folder of the repository is named there."""
    import re

    root = PACKAGE.parent
    text = (root / "README.md").read_text()
    block = text.split("## Layout", 1)[1].split("```", 2)[1]
    # The first column of each line, and modules named in a description ("...; simgen/x.py: ...").
    named = {line.split()[0].rstrip("/") for line in block.splitlines() if line and not line[0].isspace()}
    named |= set(re.findall(r"simgen/\w+\.py", block))
    assert named, "no layout block found"
    for name in named:
        assert (root / name).exists(), f"README layout names {name}, which does not exist"
    public = {f"simgen/{p.name}" for p in PACKAGE.iterdir()
              if not p.name.startswith("_") and (p.suffix == ".py" or (p / "__init__.py").exists())}
    top = {p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and p.name != "simgen"
           and not p.name.endswith(".egg-info") and p.name not in ("build", "dist")}
    missing = sorted((public | top) - named)
    assert not missing, f"README layout does not name {missing}"
