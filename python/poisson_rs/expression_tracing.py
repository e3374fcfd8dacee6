"""A Hamiltonian given as a Python callable on torch tensors, traced once into the expression
grammar (:mod:`poisson_rs.expressions`), so the Rust core steps it as it steps a string.

The callable is called once, on a symbolic state: ``x[..., i]`` (or ``x[i]``: the state traced is
one (n,) vector, so both name coordinate i), ``x.unbind(-1)`` and slices give coordinates;
``+ - * /``, ``**`` with a number as the exponent, ``torch.exp log sin cos tan sqrt tanh`` (or
the Tensor methods, or NumPy's functions of the same names), ``torch.square``, ``torch.pow``,
``torch.sum`` / ``.sum(-1)`` over the coordinates, and numbers (Python, NumPy, one-element
tensors) combine them. What it returns, one number, is printed as text in the grammar (the
evaluation order kept by parentheses), then parsed with every bound the grammar has. So the
callable must be straight-line arithmetic: branching on a state (``if x[0] > 0``), ``abs``,
``max``, ``math.sin`` and other torch functions are refused in one ValueError naming the
operation, never evaluated.

    H = lambda x: 0.5 * x[..., 0] ** 2 - torch.cos(x[..., 1])
    system = pr.with_hamiltonian(structure, H)   # system.h.text: "0.5*x1**2 - cos(x2)"

The same callable stays a torch function: autograd of it at any batch is the independent oracle
of the core's ∇H (the tests do that).
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .expressions import FUNCTIONS, MAX_CHARS, ExpressionError

__all__ = ["trace_hamiltonian", "tracing_names"]

# Precedence of a printed node: what an operand must reach to go without parentheses.
_SUM, _PRODUCT, _UNARY, _POWER, _ATOM = 1, 2, 3, 4, 5


class TraceError(ExpressionError):
    """A callable the tracer cannot write in the grammar."""


def _number(value: Any, what: str) -> float:
    """A plain number from a Python, NumPy or one-element torch constant."""
    if isinstance(value, (bool, np.bool_)):
        raise TraceError(f"hamiltonian: a boolean ({what}) is not a number of the grammar")
    if isinstance(value, numbers.Real):
        try:
            v = float(value)
        except OverflowError:
            raise TraceError(f"hamiltonian: the constant {value!r} overflows float64") from None
    elif getattr(value, "numel", None) is not None and value.numel() == 1:
        v = float(value.detach().reshape(()).item())
    elif isinstance(value, np.ndarray) and value.size == 1:
        v = float(value.reshape(()))
    else:
        raise TraceError(
            f"hamiltonian: cannot combine the state with {type(value).__name__} ({what})"
        )
    if not math.isfinite(v):
        raise TraceError(f"hamiltonian: the constant {v} is not finite")
    return v


class _Arithmetic:
    """The operators and functions a traced value takes, each in terms of its ``_binary``,
    ``__pow__`` and ``apply`` (a number's, or a vector's elementwise)."""

    __slots__ = ()

    def _binary(self, other: Any, op: str, reverse: bool) -> Any:
        raise NotImplementedError

    def apply(self, name: str) -> Any:
        raise NotImplementedError

    def __add__(self, o: Any) -> Any:
        return self._binary(o, "+", False)

    def __radd__(self, o: Any) -> Any:
        return self._binary(o, "+", True)

    def __sub__(self, o: Any) -> Any:
        return self._binary(o, "-", False)

    def __rsub__(self, o: Any) -> Any:
        return self._binary(o, "-", True)

    def __mul__(self, o: Any) -> Any:
        return self._binary(o, "*", False)

    def __rmul__(self, o: Any) -> Any:
        return self._binary(o, "*", True)

    def __truediv__(self, o: Any) -> Any:
        return self._binary(o, "/", False)

    def __rtruediv__(self, o: Any) -> Any:
        return self._binary(o, "/", True)

    def __pos__(self) -> Any:
        return self

    def exp(self) -> Any:
        return self.apply("exp")

    def log(self) -> Any:
        return self.apply("log")

    def sin(self) -> Any:
        return self.apply("sin")

    def cos(self) -> Any:
        return self.apply("cos")

    def tan(self) -> Any:
        return self.apply("tan")

    def sqrt(self) -> Any:
        return self.apply("sqrt")

    def tanh(self) -> Any:
        return self.apply("tanh")

    def square(self) -> Any:
        return self**2  # type: ignore[operator]

    # --- what a traced value cannot do ------------------------------------------------------
    def __bool__(self) -> bool:
        raise TraceError(
            "hamiltonian: the callable branches on the state (a comparison or `if`); H must be "
            "straight-line arithmetic"
        )

    def __float__(self) -> float:
        raise TraceError(
            "hamiltonian: the callable turns the state into a float (math.* or float()); use "
            "torch's functions (torch.sin, ...)"
        )

    def _refuse(self, *_: Any) -> Any:
        raise TraceError(
            "hamiltonian: comparisons, abs, min and max are not in the grammar (H must be smooth)"
        )

    __lt__ = __le__ = __gt__ = __ge__ = __abs__ = _refuse
    __index__ = __int__ = __float__


class _Sym(_Arithmetic):
    """One traced number: its text and the precedence of its outermost operation."""

    __slots__ = ("prec", "text")

    def __init__(self, text: str, prec: int) -> None:
        self.text = text
        self.prec = prec

    # --- printing ---------------------------------------------------------------------------
    def at(self, prec: int) -> str:
        return self.text if self.prec >= prec else f"({self.text})"

    @staticmethod
    def of(value: Any, what: str) -> _Sym:
        if isinstance(value, _Sym):
            return value
        v = _number(value, what)
        if v < 0 or (v == 0 and math.copysign(1.0, v) < 0):
            return _Sym(f"-{-v!r}", _UNARY)
        return _Sym(repr(v), _ATOM)

    # --- arithmetic -------------------------------------------------------------------------
    def _binary(self, other: Any, op: str, reverse: bool) -> Any:
        if isinstance(other, _Vec):
            return other._binary(self, op, not reverse)
        a, b = (_Sym.of(other, op), self) if reverse else (self, _Sym.of(other, op))
        if op in "+-":
            return _Sym(f"{a.at(_SUM)} {op} {b.at(_PRODUCT)}", _SUM)
        return _Sym(f"{a.at(_PRODUCT)}{op}{b.at(_UNARY)}", _PRODUCT)

    def __neg__(self) -> _Sym:
        return _Sym(f"-{self.at(_UNARY)}", _UNARY)

    def __pow__(self, e: Any) -> _Sym:
        if isinstance(e, (_Sym, _Vec)):
            raise TraceError(
                "hamiltonian: an exponent must be a number (write exp(y*log(x)) for x**y)"
            )
        v = _number(e, "**")
        text = repr(float(v)) if v != int(v) else str(int(v))
        return _Sym(f"{self.at(_ATOM)}**{text}", _POWER)

    def __rpow__(self, base: Any) -> _Sym:
        b = _number(base, "**")
        if b <= 0:
            raise TraceError(f"hamiltonian: {b}**(state) is not a real power; write exp(...)")
        return (_Sym.of(math.log(b), "**") * self).exp() if b != math.e else self.exp()

    def apply(self, name: str) -> _Sym:
        return _Sym(f"{name}({self.text})", _ATOM)

    def sum(self, *args: Any, **kwargs: Any) -> _Sym:
        return self


class _Vec(_Arithmetic):
    """The traced state, or an elementwise result on it: a list of numbers (coordinates)."""

    __slots__ = ("items",)

    def __init__(self, items: Sequence[_Sym]) -> None:
        self.items = list(items)

    @property
    def shape(self) -> tuple[int, ...]:
        return (len(self.items),)

    def __len__(self) -> int:
        return len(self.items)

    def __iter__(self) -> Any:
        return iter(self.items)

    def __getitem__(self, key: Any) -> Any:
        if isinstance(key, tuple):
            rest = [k for k in key if k is not Ellipsis]
            if len(rest) != 1 or (len(key) == 2 and key[-1] is Ellipsis):
                raise TraceError(
                    f"hamiltonian: index the state by one coordinate (x[..., i]), got {key!r}"
                )
            key = rest[0]
        if isinstance(key, slice):
            return _Vec(self.items[key])
        if isinstance(key, (bool, np.bool_)) or not isinstance(key, numbers.Integral):
            raise TraceError(f"hamiltonian: index the state by an integer, got {key!r}")
        try:
            return self.items[int(key)]
        except IndexError:
            raise TraceError(
                f"hamiltonian: coordinate {int(key)} does not exist (dimension {len(self)})"
            ) from None

    def unbind(self, dim: int = 0) -> tuple[_Sym, ...]:
        return tuple(self.items)

    def sum(self, *args: Any, **kwargs: Any) -> _Sym:
        out = self.items[0] if self.items else _Sym("0.0", _ATOM)
        for s in self.items[1:]:
            out = out + s
        return out

    def _binary(self, other: Any, op: str, reverse: bool) -> _Vec:
        pairs: list[tuple[_Sym, Any]]
        if isinstance(other, _Vec):
            if len(other) != len(self):
                raise TraceError(f"hamiltonian: {op} of {len(self)} and {len(other)} numbers")
            pairs = list(zip(self.items, other.items, strict=True))
        elif isinstance(other, _Sym) or np.ndim(_host(other)) == 0:
            pairs = [(s, other) for s in self.items]
        else:
            values = np.asarray(_host(other), dtype=np.float64).ravel()
            if len(values) != len(self):
                raise TraceError(
                    f"hamiltonian: {op} of the state's {len(self)} numbers and {len(values)}"
                )
            pairs = list(zip(self.items, values.tolist(), strict=True))
        return _Vec([s._binary(o, op, reverse) for s, o in pairs])

    def __neg__(self) -> _Vec:
        return _Vec([-s for s in self.items])

    def __pow__(self, e: Any) -> _Vec:
        return _Vec([s**e for s in self.items])

    def apply(self, name: str) -> _Vec:
        return _Vec([s.apply(name) for s in self.items])


def _host(value: Any) -> Any:
    """A torch constant as NumPy (for elementwise constants); anything else unchanged."""
    detach = getattr(value, "detach", None)
    return detach().cpu().numpy() if callable(detach) else value


def _torch_function(cls: Any, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
    """torch.sin(traced) and friends: the grammar's functions, sums, powers and arithmetic."""
    kwargs = kwargs or {}
    name = getattr(func, "__name__", str(func)).rstrip("_")
    if name in FUNCTIONS or name in ("square", "sum", "unbind", "neg"):
        return getattr(args[0], name if name != "neg" else "__neg__")()
    if name == "pow":
        return args[0] ** args[1]
    binary = {"add": "__add__", "sub": "__sub__", "mul": "__mul__", "div": "__truediv__"}
    if name in binary and len(args) == 2 and not kwargs:
        a, b = args
        if isinstance(a, (_Sym, _Vec)):
            return getattr(a, binary[name])(b)
        return getattr(b, "__r" + binary[name][2:])(a)
    if name in ("__getitem__",):
        return args[0][args[1]]
    raise TraceError(
        f"hamiltonian: torch.{name} is not in the grammar; the callable may use + - * / **, "
        f"{', '.join(FUNCTIONS)}, square, pow, sum and indexing"
    )


_UFUNCS = {
    "add": "__add__", "subtract": "__sub__", "multiply": "__mul__", "true_divide": "__truediv__",
    "divide": "__truediv__", "power": "__pow__",
}  # fmt: skip


def _array_ufunc(self: Any, ufunc: Any, method: str, *args: Any, **kwargs: Any) -> Any:
    """np.sin(traced) and NumPy's arithmetic, as torch's (for H written with NumPy)."""
    name = ufunc.__name__
    if method == "__call__" and not kwargs:
        if name in FUNCTIONS or name in ("square", "negative"):
            return getattr(args[0], "__neg__" if name == "negative" else name)()
        if name in _UFUNCS and len(args) == 2:
            a, b = args
            if isinstance(a, (_Sym, _Vec)):
                return getattr(a, _UFUNCS[name])(b)
            if name == "power":
                return b.__rpow__(a)
            return getattr(b, "__r" + _UFUNCS[name][2:])(a)
    raise TraceError(f"hamiltonian: numpy.{name} is not in the grammar")


for _cls in (_Sym, _Vec):
    setattr(_cls, "__torch_function__", classmethod(_torch_function))  # noqa: B010
    setattr(_cls, "__array_ufunc__", _array_ufunc)  # noqa: B010


def tracing_names(component_names: Sequence[str]) -> tuple[str, ...]:
    """The names the traced text uses for the coordinates: the components' own where each is a
    name the grammar reads (and none is another coordinate's x1 … xn), else x1 … xn."""
    names = tuple(component_names)
    n = len(names)
    aliases = tuple(f"x{i + 1}" for i in range(n))
    readable = all(
        re.fullmatch(r"[^\W\d]\w*", v) and v not in FUNCTIONS and v != "pi" for v in names
    )
    clash = any(v in aliases and aliases.index(v) != i for i, v in enumerate(names))
    if readable and len(set(names)) == n and not clash:
        return names
    if clash:
        raise ExpressionError(
            "hamiltonian: the components are named x1 … xn in another order; name them "
            "otherwise to pass H as a callable"
        )
    return aliases


def trace_hamiltonian(fn: Callable[[Any], Any], names: Sequence[str]) -> str:
    """The text of H = ``fn(x)`` in the coordinates ``names`` (one per coordinate, each a name
    the grammar reads): ``fn`` is called once on the symbolic state. ExpressionError (a
    ValueError) naming the operation the grammar lacks, or when the text would exceed its
    length bound."""
    if not callable(fn):
        raise ExpressionError(f"hamiltonian must be a string or a callable, got {fn!r}")
    state = _Vec([_Sym(n, _ATOM) for n in names])
    try:
        out = fn(state)
    except ExpressionError:
        raise
    except RecursionError:
        raise TraceError("hamiltonian: the callable's expression nests too deeply") from None
    except Exception as err:  # what the callable itself raised on the symbolic state
        raise TraceError(
            f"hamiltonian: the callable failed on the traced state ({type(err).__name__}: "
            f"{err}); it may use + - * / **, {', '.join(FUNCTIONS)}, square, pow, sum and "
            "indexing x[..., i]"
        ) from None
    if isinstance(out, np.ndarray) and out.dtype == object and out.size == 1:
        out = out.reshape(()).item()  # NumPy's functions on the traced state
    if isinstance(out, _Vec):
        if len(out) != 1:
            raise TraceError(
                f"hamiltonian: the callable returns {len(out)} numbers, not one (sum them?)"
            )
        out = out.items[0]
    text = _Sym.of(out, "the result").text
    if len(text) > MAX_CHARS:
        raise TraceError(
            f"hamiltonian: the traced H is {len(text)} characters as text, more than {MAX_CHARS}"
        )
    return text
