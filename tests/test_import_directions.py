"""Import directions (docs/architecture.md): read from the source with an AST walk, function-local
imports included, so the rules hold whether or not a code path runs.

- no import from a lower family to a higher one (``FAMILIES``, lowest first);
- no import loops between scenegen modules;
- the core (scenegen/core/) imports only numpy-level libraries and scenegen's schema, asset catalog
  and paths: never MuJoCo, a renderer, torch or a stage;
- the MuJoCo back end (scenegen/sim/world.py) imports the core, the schema and the catalog, never a stage;
- the generator's encoding and cost import only the core, the schema and the catalog;
- the proposers and the generator's encoding and cost never import MuJoCo, directly or through the
  modules they import at load time.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "scenegen"
NO_MUJOCO = (
    "scenegen/core/",
    "scenegen/propose/",
    "scenegen/diffusion/encoding.py",
    "scenegen/diffusion/cost.py",
)
CORE_MAY_IMPORT = ("scenegen.core", "scenegen.schema", "scenegen.assets.catalog", "scenegen.paths")
CORE_LIBRARIES = {
    "numpy",
    "scipy",
    "fcl",
    "pyarrow",
    "hashlib",
    "json",
    "re",
    "pathlib",
    "math",
    "functools",
    "collections",
    "dataclasses",
    "__future__",
}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> set[str]:
    """Every module name ``path`` imports, at any depth of its code (relative imports resolved)."""
    tree = ast.parse(path.read_text())
    package = module_name(path).rsplit(".", 1)[0] if path.name != "__init__.py" else module_name(path)
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(
                    package.split(".")[: len(package.split(".")) - node.level + 1] + [base]
                ).strip(".")
            found.add(base)
            found |= {f"{base}.{alias.name}" for alias in node.names}  # `from scenegen import world`
    return found


def graph() -> dict[str, set[str]]:
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {name: {m for m in imports(path) if m in modules and m != name} for name, path in modules.items()}


# The families, lowest first (docs/architecture.md). A module belongs to the family of its longest
# matching prefix ("scenegen" itself: the package's face only); it may import its own family and those
# below, never one above. A new module must be placed here.
FAMILIES = (
    ("base", ("scenegen", "scenegen.paths", "scenegen.devices", "scenegen.schema", "scenegen.assets")),
    ("core", ("scenegen.core",)),
    ("MuJoCo back end", ("scenegen.sim",)),
    ("generator", ("scenegen.diffusion",)),
    ("propose", ("scenegen.propose",)),
    ("check", ("scenegen.check",)),
    ("settle", ("scenegen.settle",)),
    ("tag", ("scenegen.tags",)),
    ("render", ("scenegen.render",)),
    ("store", ("scenegen.store",)),
    ("analysis", ("scenegen.analysis", "scenegen.manifest")),
    ("runner", ("scenegen.runner",)),
    (
        "data tools",
        (
            "scenegen.data",
            "scenegen.audit",
            "scenegen.assets.authoring",
            "scenegen.assets.measure",
        ),
    ),
    ("report", ("scenegen.report",)),
    ("env", ("scenegen.env",)),
    ("export", ("scenegen.export",)),
    ("perception", ("scenegen.perception",)),
    ("manipulation", ("scenegen.manipulation",)),
    ("policy", ("scenegen.policy",)),
    ("experiment", ("scenegen.experiment",)),
    ("cli", ("scenegen.cli",)),
)


def family(module: str) -> int:
    """Rank (index into FAMILIES) of the family a module belongs to, by its longest matching prefix."""
    matches = [
        (len(prefix), rank)
        for rank, (_, prefixes) in enumerate(FAMILIES)
        for prefix in prefixes
        if module == prefix or (prefix != "scenegen" and module.startswith(prefix + "."))
    ]
    assert matches, f"{module} belongs to no family: add it to FAMILIES (and to docs/architecture.md)"
    return max(matches)[1]


def test_no_import_runs_from_a_lower_family_to_a_higher_one():
    edges = graph()
    rank = {module: family(module) for module in edges}  # every module has a family
    upward = [
        f"{a} ({FAMILIES[rank[a]][0]}) imports {b} ({FAMILIES[rank[b]][0]})"
        for a, outs in sorted(edges.items())
        for b in sorted(outs)
        if rank[b] > rank[a]
    ]
    assert not upward, "imports that run up the families:\n" + "\n".join(upward)


def test_no_import_loops():
    edges = graph()
    index, low, stack, on_stack, loops, counter = {}, {}, [], set(), [], [0]

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                loops.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    assert not loops, f"import loops: {loops}"


def test_the_core_imports_no_stage_and_no_simulator():
    for path in sorted((PACKAGE / "core").rglob("*.py")):
        for name in imports(path):
            top = name.split(".")[0]
            if top == "scenegen":
                assert name == "scenegen" or name.startswith(CORE_MAY_IMPORT), f"{path.name} imports {name}"
            else:
                assert top in CORE_LIBRARIES, f"{path.name} imports {name}: the core stays numpy-level"


def test_the_mujoco_back_end_imports_no_stage():
    allowed = (
        "scenegen.core",
        "scenegen.schema",
        "scenegen.assets.catalog",
        "scenegen.paths",
        "scenegen.sim",
    )
    for path in sorted((PACKAGE / "sim").glob("*.py")):
        for name in imports(path):
            if name.startswith("scenegen."):
                assert name.startswith(allowed), f"sim/{path.name} imports {name}"


def test_only_the_cli_parses_arguments():
    """Library functions take typed arguments: argparse is imported in scenegen/cli/ only (and in a
    ``python -m`` entry point's ``if __name__ == "__main__":`` block, which no library code runs)."""
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.is_relative_to(PACKAGE / "cli"):
            continue
        tree = ast.parse(path.read_text())
        main_blocks = [
            node for node in tree.body if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test)
        ]
        in_main = {id(n) for block in main_blocks for n in ast.walk(block)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import | ast.ImportFrom) and id(node) not in in_main:
                names = [a.name for a in node.names] + [getattr(node, "module", None) or ""]
                assert "argparse" not in names, f"{path.relative_to(PACKAGE.parent)} imports argparse"


def test_the_generators_encoding_and_cost_import_only_the_core_the_schema_and_the_catalog():
    allowed = CORE_MAY_IMPORT + ("scenegen.diffusion.encoding",)
    for name in ("encoding.py", "cost.py"):
        for module in imports(PACKAGE / "diffusion" / name):
            if module.startswith("scenegen."):
                assert module.startswith(allowed), f"diffusion/{name} imports {module}"


def test_the_generator_imports_no_stage_no_back_end_and_no_runner():
    """scenegen/diffusion/ (model, encoding, cost, data, sampling, training) is a component the proposers
    use: it imports only the core, the schema, the catalog, the paths, the training device and itself."""
    allowed = CORE_MAY_IMPORT + ("scenegen.devices", "scenegen.diffusion")
    for path in sorted((PACKAGE / "diffusion").glob("*.py")):
        for module in imports(path):
            if module.startswith("scenegen.") and module != "scenegen.diffusion":
                assert module.startswith(allowed), f"diffusion/{path.name} imports {module}"


def test_the_proposers_import_no_stage_and_no_back_end():
    """Proposers (and the generator they sample) sit below check, settle, tag, render, store, the
    MuJoCo back end and the runner: they import only the core, the schema, the catalog, each other
    and the generator's sampling modules."""
    allowed = CORE_MAY_IMPORT + ("scenegen.propose", "scenegen.diffusion.")
    below = ("encoding", "cost", "model", "sample", "data", "verifier")
    for path in sorted((PACKAGE / "propose").glob("*.py")):
        for module in imports(path):
            if module.startswith("scenegen.") and module != "scenegen.propose":
                assert module.startswith(allowed), f"propose/{path.name} imports {module}"
                if module.startswith("scenegen.diffusion."):
                    assert module.split(".")[2] in below, f"propose/{path.name} imports {module}"


def test_no_mujoco_import_in_the_core_the_proposers_or_the_encoding_and_cost():
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = str(path.relative_to(PACKAGE.parent))
        if relative.startswith(NO_MUJOCO):
            assert not {n for n in imports(path) if n.split(".")[0] == "mujoco"}, relative


def test_importing_the_proposers_and_the_generator_loads_no_mujoco():
    code = (
        "import sys; import scenegen.propose.procedural, scenegen.propose.targeted, "
        "scenegen.propose.diffusion, scenegen.diffusion.encoding, scenegen.diffusion.cost, "
        "scenegen.core.solids; "
        "assert 'mujoco' not in sys.modules, sorted(m for m in sys.modules if m.startswith('scenegen'))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr


MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 100


def test_modules_and_functions_stay_readable():
    """A module past 500 lines or a function past 100 is asking to be split (shared/STYLE.md)."""
    too_long = []
    for path in sorted(PACKAGE.rglob("*.py")):
        text = path.read_text()
        name = str(path.relative_to(PACKAGE.parent))
        if len(text.splitlines()) > MAX_MODULE_LINES:
            too_long.append(f"{name}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    too_long.append(f"{name}:{node.lineno} {node.name}: {lines} lines")
    assert not too_long, "split these:\n" + "\n".join(too_long)
