"""The package's layout: no module imports another that imports it back (lazily or not), and the
generic layers (studies, CLI) never name a structure family."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import poisson_rs

ROOT = Path(poisson_rs.__file__).parent


def _modules() -> dict[str, Path]:
    out = {}
    for f in ROOT.rglob("*.py"):
        parts = f.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = f
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules ``name`` imports anywhere: at the top, inside functions, under
    ``if TYPE_CHECKING``; each resolved to the deepest module it names (``from . import x``
    names ``pkg.x`` when that is a module). The package root (imported first anyway) is left
    out."""
    base = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                parts = base.split(".")
                target = ".".join(parts[: len(parts) - node.level + 1])
                target += f".{node.module}" if node.module else ""
            else:
                target = node.module or ""
            candidates = [*(f"{target}.{a.name}" for a in node.names), target]
        elif isinstance(node, ast.Import):
            candidates = [a.name for a in node.names]
        else:
            continue
        for c in candidates:
            while c and c not in modules:
                c = c.rpartition(".")[0]
            if c and c not in (name, "poisson_rs"):
                found.add(c)
    return found


#: Cycles the layout still has, each with why it stays: {the modules in it: why}.
ALLOWED_CYCLES: dict[frozenset[str], str] = {}


def _cycles(edges: dict[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[frozenset[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(frozenset(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def _edges() -> dict[str, set[str]]:
    modules = _modules()
    return {m: _imports(m, p, modules) for m, p in modules.items()}


def test_no_import_cycles_between_modules() -> None:
    """Imports point one way (structures, realizations, generating functions, steppers,
    rollout, studies, CLI): no module reaches itself through the package's imports, those
    inside functions and under TYPE_CHECKING included."""
    cycles = [sorted(c) for c in _cycles(_edges()) if c not in ALLOWED_CYCLES]
    assert not cycles, cycles


def test_the_import_graph_sees_every_import() -> None:
    edges = _edges()
    # Imported inside a method only.
    assert "poisson_rs.casimirs" in edges["poisson_rs.structures.affine"]
    # ``from . import x`` of a submodule names the submodule.
    assert "poisson_rs.studies.figures" in edges["poisson_rs.cli.demo"]
    assert _cycles({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == [frozenset({"a", "b"})]


def test_allowed_cycles_are_still_cycles() -> None:
    """An exception that no longer holds is dropped from ALLOWED_CYCLES."""
    found = set(_cycles(_edges()))
    assert all(c in found for c in ALLOWED_CYCLES), set(ALLOWED_CYCLES) - found


FAMILY_CHECK = re.compile(
    r"is_log_canonical|is_affine|is_polynomial_bivector|is_positive_orthant|isinstance\([^)]*"
    r"(RigidBody|HeavyTop|LiePoissonSystem|LogCanonicalSystem|AffinePoissonSystem|"
    r"PolynomialPoissonSystem|ChargedParticle)"
)


#: The modules that serve every structure: no family named in them.
GENERIC = (
    "studies/*.py",
    "cli/*.py",
    "learn/*.py",
    "rollout.py",
    "scenes.py",
    "reference.py",
    "model_files.py",
    "protocols.py",
    "ensembles.py",
    "casimirs.py",
    "bracket_family.py",
    "hamiltonian_family.py",
    "hamiltonian_library.py",
)


def test_generic_layers_never_name_a_structure_family() -> None:
    generic = [f for pattern in GENERIC for f in ROOT.glob(pattern)]
    assert len(generic) > 30  # the patterns still match the layout
    found = [
        f"{f.name}:{k + 1}"
        for f in generic
        for k, line in enumerate(f.read_text(encoding="utf-8").splitlines())
        if FAMILY_CHECK.search(line)
    ]
    assert not found, found


def test_the_fifth_structure_is_named_by_its_own_module_only() -> None:
    named = [
        f.relative_to(ROOT).as_posix()
        for f in ROOT.rglob("*.py")
        if re.search(r"charged_particle|ChargedParticle", f.read_text(encoding="utf-8"))
    ]
    assert named == ["structures/charged_particle.py"]
