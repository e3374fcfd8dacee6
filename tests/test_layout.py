"""The package's layout: no module imports another that imports it back at import time, and the
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


def _top_level_imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules ``name`` imports when it is imported (not inside functions, not
    for type checking); the package root (imported first anyway) is left out."""
    base = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found: set[str] = set()
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:
            parts = base.split(".")
            target = ".".join(parts[: len(parts) - node.level + 1])
            target += f".{node.module}" if node.module else ""
        else:
            target = node.module or ""
        candidates = [target, *(f"{target}.{a.name}" for a in node.names)]
        found.update(c for c in candidates if c in modules and c not in (name, "poisson_rs"))
    return found


def test_no_import_cycles_at_import_time() -> None:
    modules = _modules()
    edges = {m: _top_level_imports(m, p, modules) for m, p in modules.items()}

    def reaches(start: str, goal: str) -> bool:
        seen, todo = set(), [start]
        while todo:
            m = todo.pop()
            if m == goal:
                return True
            if m not in seen:
                seen.add(m)
                todo.extend(edges[m])
        return False

    cycles = [(a, b) for a in edges for b in edges[a] if reaches(b, a)]
    assert not cycles, cycles


FAMILY_CHECK = re.compile(
    r"is_log_canonical|is_affine|is_polynomial_bivector|is_positive_orthant|isinstance\([^)]*"
    r"(RigidBody|HeavyTop|LiePoissonSystem|LogCanonicalSystem|AffinePoissonSystem|"
    r"PolynomialPoissonSystem|ChargedParticle)"
)


def test_generic_layers_never_name_a_structure_family() -> None:
    generic = [*ROOT.glob("studies/*.py"), *ROOT.glob("cli/*.py"), ROOT / "rollout.py"]
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
