"""The expression grammar of non-polynomial Hamiltonians (poisson_rs.expressions): every operator
against NumPy's closed forms, the core's exact ∇H and ∇²H against torch autograd, the bounds,
and hostile text refused in one line without ``eval``."""

from __future__ import annotations

import builtins
import pickle

import numpy as np
import pytest
import torch

from poisson_rs import _core
from poisson_rs.expressions import (
    MAX_CHARS,
    MAX_DEPTH,
    MAX_INSTRUCTIONS,
    MAX_LIVE,
    MAX_POWER,
    OPCODES,
    Expression,
    ExpressionError,
    evaluate_table,
    field_program,
    live_values,
    parse_program,
)

NAMES = ("u", "v", "r")
ALIASES = ("x1", "x2", "x3")

#: text → the same function written in NumPy, on positive-enough states.
CASES = {
    "u + v - r": lambda u, v, r: u + v - r,
    "u * v / r": lambda u, v, r: u * v / r,
    "-u + +v": lambda u, v, r: -u + v,
    "u**3 - v^2 + r**-2": lambda u, v, r: u**3 - v**2 + r**-2.0,
    "u**(-1.5) + v**0.5 + r**2.25": lambda u, v, r: u**-1.5 + np.sqrt(v) + r**2.25,
    "exp(u) * log(v) + sin(r) - cos(u*v)": lambda u, v, r: (
        np.exp(u) * np.log(v) + np.sin(r) - np.cos(u * v)
    ),
    "tan(u/3) + sqrt(1 + v**2) + tanh(r - 1)": lambda u, v, r: (
        np.tan(u / 3) + np.sqrt(1 + v**2) + np.tanh(r - 1)
    ),
    "pi * x1 + 2.5e-1 * x3 - .5": lambda u, v, r: np.pi * u + 0.25 * r - 0.5,
    "u**2/2 - cos(v) + u*(r - u**2 - v**2)": lambda u, v, r: (
        u**2 / 2 - np.cos(v) + u * (r - u**2 - v**2)
    ),
}


def _states(n: int = 16, seed: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.3, 1.7, size=(n, 3))


@pytest.mark.parametrize("text", list(CASES))
def test_every_operator_matches_numpy(text: str) -> None:
    x = _states()
    e = Expression(text, NAMES, aliases=ALIASES)
    np.testing.assert_allclose(e(x), CASES[text](*x.T), rtol=1e-14, atol=1e-14)


def _assert_core_jets_match_autograd(e: Expression, x: np.ndarray, atol: float) -> None:
    """The core's H, ∇H and ∇²H of ``e`` at the rows of ``x`` against torch autograd's."""
    value, grad, hess = _core.expression_jets(*e.tape(), np.ascontiguousarray(x))
    for k in range(len(x)):
        xt = torch.tensor(x[k], dtype=torch.float64, requires_grad=True)
        h = e.evaluate(xt, torch)
        (g,) = torch.autograd.grad(h, xt)
        hs = torch.autograd.functional.hessian(lambda y: e.evaluate(y, torch), xt)
        np.testing.assert_allclose(value[k], h.item(), rtol=1e-13)
        np.testing.assert_allclose(grad[k], g.numpy(), rtol=1e-12, atol=atol)
        np.testing.assert_allclose(hess[k], hs.numpy(), rtol=1e-11, atol=10 * atol)


@pytest.mark.parametrize("text", list(CASES))
def test_core_gradient_and_hessian_match_autograd(text: str) -> None:
    _assert_core_jets_match_autograd(Expression(text, NAMES, aliases=ALIASES), _states(6), 1e-13)


def test_common_subexpressions_are_shared_and_constants_folded() -> None:
    e = Expression("sin(u) + sin(u) + 2*3", NAMES)
    assert [n[0] for n in e.program].count("sin") == 1
    assert ("const", 6.0) in e.program
    assert e.program[-1][0] == "add"


def test_a_field_program_shares_products_that_differ_by_a_constant_factor() -> None:
    """ẋ = π∇H for H = ln((x1 − x3)² + (x2 − x4)²) on the canonical pairs: the chain rule gives
    ±2·(1/r²)·dx and ±2·(1/r²)·dy; with the constants moved out the program holds one product
    (1/r²)·dx and one (1/r²)·dy, and the field still equals autograd's."""
    h = Expression("log((x1 - x3)**2 + (x2 - x4)**2)", ("x1", "x2", "x3", "x4"))
    # π_01 = π_23 = 1 (upper triangle, row by row: (0,1) is pair 0, (2,3) is pair 5).
    index = np.array([0, 5], dtype=np.int64)
    coeffs = np.array([1.0, 1.0])
    exponents = np.zeros((2, 4), dtype=np.int64)
    code, a, b, c, outputs = field_program(h, index, coeffs, exponents)
    nodes = [(OPCODES[k], int(i), int(j)) for k, i, j in zip(code, a, b, strict=True)]
    consts = {k for k, n in enumerate(nodes) if n[0] == "const"}
    products = [n for n in nodes if n[0] == "mul" and not {n[1], n[2]} & consts]
    assert len(products) == 2, nodes
    x = np.random.default_rng(2).uniform(-1.0, 1.0, size=(16, 4))
    xt = torch.tensor(x, requires_grad=True)
    (g,) = torch.autograd.grad(h.evaluate(xt, torch).sum(), xt)
    g = g.numpy()
    want = np.stack([g[:, 1], -g[:, 0], g[:, 3], -g[:, 2]], axis=-1)
    got = evaluate_table((code, a, b, c), outputs, x)
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)


def test_names_and_aliases_refer_to_the_same_coordinate() -> None:
    x = _states(4)
    a = Expression("u*r", NAMES, aliases=ALIASES)
    b = Expression("x1*x3", NAMES, aliases=ALIASES)
    np.testing.assert_array_equal(a(x), b(x))
    assert a.uses() == (0, 2)


def test_pickle_keeps_the_program() -> None:
    e = Expression("exp(u) - v**3", NAMES, aliases=ALIASES)
    back = pickle.loads(pickle.dumps(e))
    assert back == e and back.program == e.program


HOSTILE = [
    "__import__('os').system('true')",
    "u; import os",
    "lambda: 0",
    "u.real",
    "[u]",
    "u if v else r",
    "open('x')",
    "eval('1')",
    "u @ v",
    "u $ v",
    "\\x41",
    "u == v",
    "",
    "   ",
    "u +",
    "(u",
    "u)",
    "sin u",
    "sin()",
    "u**v",
    "u**2**2",
    "w + 1",
    "1e999",
    "exp(1000)",
    "log(-1)",
    "1/0",
    "sqrt(-1)",
]


@pytest.mark.parametrize("text", HOSTILE)
def test_hostile_or_malformed_text_is_refused_in_one_line(
    text: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    def forbidden(*args: object, **kwargs: object) -> None:
        raise AssertionError("eval/exec must never run")

    monkeypatch.setattr(builtins, "eval", forbidden)
    monkeypatch.setattr(builtins, "exec", forbidden)
    with pytest.raises(ExpressionError) as info:
        Expression(text, NAMES)
    message = str(info.value)
    assert message.startswith("hamiltonian") and "\n" not in message


def test_bounds_are_refused_with_their_number() -> None:
    with pytest.raises(ExpressionError, match=f"longer than {MAX_CHARS}"):
        Expression("u+" * (MAX_CHARS // 2) + "u", NAMES)
    with pytest.raises(ExpressionError, match=f"deeper than {MAX_DEPTH}"):
        Expression("(" * (MAX_DEPTH + 1) + "u" + ")" * (MAX_DEPTH + 1), NAMES)
    long = " + ".join(f"sin({k}*u)" for k in range(1, MAX_INSTRUCTIONS))
    with pytest.raises(ExpressionError, match=f"more than {MAX_INSTRUCTIONS} instructions"):
        Expression(long, NAMES)
    with pytest.raises(ExpressionError, match="outside"):
        Expression(f"u**{MAX_POWER + 1}", NAMES)
    with pytest.raises(ExpressionError, match="outside"):
        Expression(f"u**-{MAX_POWER}.5", NAMES)
    Expression(f"u**{MAX_POWER}", NAMES)
    with pytest.raises(ExpressionError, match="must be a string"):
        Expression(3, NAMES)  # type: ignore[arg-type]


#: A sum of 69 short terms: over 256 instructions, a handful of values live at once.
LONG = " + ".join(f"{0.1 + k / 97:.6f}*sin({k}*u + v)*r" for k in range(1, 70))
#: Two sums over the same constants 2 … 9: the second reads each again.
WIDE = " + ".join([*(f"{k}*u" for k in range(2, 10)), *(f"{k}*v" for k in range(2, 10))])


def test_a_long_sum_is_evaluated_by_the_core_against_autograd() -> None:
    e = Expression(LONG, NAMES)
    assert len(e.program) > MAX_LIVE and live_values(e.program) < 10
    _assert_core_jets_match_autograd(e, _states(4), 1e-12)


def test_live_values_count_the_core_slots() -> None:
    # u·v + sin(u): the product takes v's slot (v read last there), the sine u's.
    assert live_values(parse_program("u*v + sin(u)", NAMES)) == 2
    # A sum as it is made keeps u, the running sum and one term.
    assert live_values(parse_program(" + ".join(f"{k}*u" for k in range(2, 200)), NAMES)) == 3
    # The constants 2 … 9 are read again by the second sum: live across it.
    assert live_values(parse_program(WIDE, NAMES)) >= 8 + 2


def test_values_live_beyond_the_limit_are_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    import poisson_rs.expressions as ex

    monkeypatch.setattr(ex, "MAX_LIVE", 8)
    with pytest.raises(ExpressionError, match=r"^hamiltonian: .* values live at once, more than 8"):
        Expression(WIDE, NAMES)
    Expression(" + ".join(f"{k}*u" for k in range(2, 200)), NAMES)


def test_the_core_refuses_a_forged_tape() -> None:
    code, a, b, c = Expression("u*v", NAMES).tape()
    x = np.ones((1, 3))
    bad = a.copy()
    bad[-1] = len(a) + 5  # an operand after its instruction
    with pytest.raises(ValueError, match="earlier instruction"):
        _core.expression_jets(code, bad, b, c, x)
    code2 = code.copy()
    code2[0] = 99
    with pytest.raises(ValueError, match="unknown opcode"):
        _core.expression_jets(code2, a, b, c, x)
    c2 = c.copy()
    code3 = code.copy()
    code3[0], c2[0] = 1, np.nan
    with pytest.raises(ValueError, match="not finite"):
        _core.expression_jets(code3, a, b, c2, x)
