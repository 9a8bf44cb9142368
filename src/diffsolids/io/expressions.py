"""PolyFEM's value expressions of x, y, z, t, parsed without ``eval`` and evaluated with numpy.

PolyFEM evaluates a string value (a Dirichlet or obstacle displacement component, a load) with
TinyExpr (codeplea/tinyexpr, built without ``TE_NAT_LOG`` and ``TE_POW_FROM_RIGHT``) and the
variables x, y, z, t plus a few functions of its own (``polyfem/utils/ExpressionValue.cpp``).
:func:`parse_expression` reads the same grammar into a tree of numpy operations (a whitelist:
no Python ``eval``, no attribute access, no names other than those below) that is evaluated
vectorised, e.g. over every vertex of an obstacle at once::

    list   = expr                                 (TinyExpr's "," list operator is refused)
    expr   = term {("+" | "-") term}
    term   = factor {("*" | "/" | "%") factor}
    factor = power {"^" power}                    (left to right: 2^3^2 = (2^3)^2 = 64)
    power  = {"+" | "-"} base                     (the sign binds tighter: -2^2 = (-2)^2 = 4)
    base   = number | variable | constant ["(" ")"] | function1 power
           | functionN "(" expr {"," expr} ")" | "(" expr ")"

So TinyExpr's rules, which differ from Python's in three places: ``^`` is left-associative, a
leading sign belongs to the base it precedes (``-x^2`` is ``(-x)^2``), and a one-argument
function takes the next power without parentheses (``sin x^2`` is ``(sin x)^2``, ``sqrt 4``
is 2). Numbers are decimal (``2``, ``.5``, ``1e-3``, ``3.``); hexadecimal is refused.

Names: the variables ``x y z t``; the constants ``pi`` and ``e`` (``pi()`` works too);
TinyExpr's functions ``abs acos asin atan atan2 ceil cos cosh exp floor ln log log10 pow sin
sinh sqrt tan tanh`` (``log`` is the base-10 logarithm, as TinyExpr's default and therefore
PolyFEM's; ``ln`` is the natural one; ``%`` is C's fmod); PolyFEM's ``min max sign
smoothstep half_smoothstep deg2rad rotate_2D_x rotate_2D_y if compare smooth_abs`` (``if(c, a,
b)`` is a where c >= 0, else b; ``compare(a, b)`` is 1 where a < b, else 0). TinyExpr's ``fac``,
``ncr`` and ``npr`` are refused by name (integer loops, not needed for motions).
"""

import math
import operator
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from diffsolids.errors import ParameterError

__all__ = ["VARIABLES", "Expression", "ExpressionError", "parse_expression"]

VARIABLES = ("x", "y", "z", "t")


class ExpressionError(ParameterError):
    """An expression that does not parse (the message names the character where it fails)."""


def _smoothstep(a: np.ndarray) -> np.ndarray:
    return np.where(a < 0, 0.0, np.where(a > 1, 1.0, 3 * a**2 - 2 * a**3))


# name -> (arity, numpy implementation); arity 0 is a constant (TinyExpr's TE_FUNCTION0)
_FUNCTIONS: dict[str, tuple[int, Callable[..., np.ndarray]]] = {
    "abs": (1, np.abs),
    "acos": (1, np.arccos),
    "asin": (1, np.arcsin),
    "atan": (1, np.arctan),
    "atan2": (2, np.arctan2),
    "ceil": (1, np.ceil),
    "cos": (1, np.cos),
    "cosh": (1, np.cosh),
    "e": (0, lambda: np.float64(math.e)),
    "exp": (1, np.exp),
    "floor": (1, np.floor),
    "ln": (1, np.log),
    "log": (1, np.log10),  # TinyExpr without TE_NAT_LOG (PolyFEM's build)
    "log10": (1, np.log10),
    "pi": (0, lambda: np.float64(math.pi)),
    "pow": (2, np.power),
    "sin": (1, np.sin),
    "sinh": (1, np.sinh),
    "sqrt": (1, np.sqrt),
    "tan": (1, np.tan),
    "tanh": (1, np.tanh),
    # PolyFEM's additions (ExpressionValue.cpp)
    "min": (2, lambda a, b: np.where(a < b, a, b)),
    "max": (2, lambda a, b: np.where(a > b, a, b)),
    "smoothstep": (1, _smoothstep),
    "half_smoothstep": (1, lambda a: 2.0 * _smoothstep((a + 1.0) / 2.0) - 1.0),
    "deg2rad": (1, lambda d: d * math.pi / 180.0),
    "rotate_2D_x": (3, lambda x, y, th: x * np.cos(th) - y * np.sin(th)),
    "rotate_2D_y": (3, lambda x, y, th: x * np.sin(th) + y * np.cos(th)),
    "if": (3, lambda c, a, b: np.where(c >= 0, a, b)),
    "compare": (2, lambda a, b: np.where(a < b, 1.0, 0.0)),
    "smooth_abs": (2, lambda x, k: np.tanh(k * x) * x),
    "sign": (1, lambda a: (a > 0).astype(float) - (a < 0).astype(float)),
}
_REFUSED = {"fac", "ncr", "npr"}
_UFL = "__ufl__"  # the env key that selects the UFL implementations


def _ufl_functions() -> dict[str, Callable]:
    """UFL implementations of the differentiable functions (for :meth:`Expression.ufl`)."""
    import ufl

    return {
        "abs": abs,
        "acos": ufl.acos,
        "asin": ufl.asin,
        "atan": ufl.atan,
        "atan2": ufl.atan2,
        "cos": ufl.cos,
        "cosh": ufl.cosh,
        "exp": ufl.exp,
        "ln": ufl.ln,
        "log": lambda a: ufl.ln(a) / math.log(10.0),
        "log10": lambda a: ufl.ln(a) / math.log(10.0),
        "pow": lambda a, b: a**b,
        "sin": ufl.sin,
        "sinh": ufl.sinh,
        "sqrt": ufl.sqrt,
        "tan": ufl.tan,
        "tanh": ufl.tanh,
        "min": ufl.min_value,
        "max": ufl.max_value,
        "deg2rad": lambda d: d * math.pi / 180.0,
        "rotate_2D_x": lambda x, y, th: x * ufl.cos(th) - y * ufl.sin(th),
        "rotate_2D_y": lambda x, y, th: x * ufl.sin(th) + y * ufl.cos(th),
        "if": lambda c, a, b: ufl.conditional(ufl.ge(c, 0), a, b),
        "smooth_abs": lambda x, k: ufl.tanh(k * x) * x,
        "sign": ufl.sign,
    }


_BINARY = {"+": np.add, "-": np.subtract, "*": np.multiply, "/": np.divide, "^": np.power}
_BINARY["%"] = np.fmod
_UFL_BINARY = {"+": operator.add, "-": operator.sub, "*": operator.mul, "/": operator.truediv}
_UFL_BINARY["^"] = operator.pow

_TOKEN = re.compile(
    r"(?P<space>[ \t\n\r]+)"
    r"|(?P<number>(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?)"
    r"|(?P<name>[A-Za-z][A-Za-z0-9_]*)"
    r"|(?P<op>[-+*/^%(),])"
)

Node = Callable[[dict], np.ndarray]


@dataclass(frozen=True)
class _Token:
    kind: str  # "number", "name", "op", "end"
    text: str
    pos: int


def _tokens(text: str) -> list[_Token]:
    out, pos = [], 0
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None:
            raise ExpressionError(
                f"expression {text!r}: unexpected character {text[pos]!r} at {pos + 1}"
            )
        kind = m.lastgroup
        if kind == "number" and re.match(r"0[xX]", text[pos:]):
            raise ExpressionError(f"expression {text!r}: hexadecimal numbers are not supported")
        if kind != "space":
            out.append(_Token(kind, m.group(), pos))
        pos = m.end()
    out.append(_Token("end", "", len(text)))
    return out


def _binary(op: str, a: Node, b: Node) -> Node:
    def node(env: dict) -> np.ndarray:
        if not env.get(_UFL):
            return _BINARY[op](a(env), b(env))
        if op not in _UFL_BINARY:
            raise ExpressionError(f"the operator {op!r} has no UFL form (not differentiable)")
        return _UFL_BINARY[op](a(env), b(env))

    return node


def _function(name: str, f: Callable, env: dict) -> Callable:
    """The implementation of a function for the env's backend (numpy or UFL)."""
    if not env.get(_UFL):
        return f
    impl = env[_UFL].get(name)
    if impl is None:
        raise ExpressionError(f"the function {name!r} has no UFL form (not differentiable)")
    return impl


class _Parser:
    """Recursive descent over TinyExpr's grammar (module docstring), building numpy closures."""

    def __init__(self, text: str) -> None:
        self.text = text
        self.tokens = _tokens(text)
        self.k = 0
        self.variables: set[str] = set()

    @property
    def tok(self) -> _Token:
        return self.tokens[self.k]

    def error(self, what: str) -> ExpressionError:
        tok = self.tok
        at = "the end" if tok.kind == "end" else f"{tok.text!r} (character {tok.pos + 1})"
        return ExpressionError(f"expression {self.text!r}: {what} at {at}")

    def is_op(self, *ops: str) -> bool:
        return self.tok.kind == "op" and self.tok.text in ops

    def parse(self) -> Node:
        if self.tok.kind == "end":
            raise ExpressionError("expression is empty")
        node = self.expr()
        if self.is_op(","):
            raise self.error("a ',' outside a function's arguments (TinyExpr's list) is refused")
        if self.tok.kind != "end":
            raise self.error("expected an operator or the end")
        return node

    def binary_chain(self, ops: tuple[str, ...], operand: Callable[[], Node]) -> Node:
        node = operand()
        while self.is_op(*ops):
            op = self.tok.text
            self.k += 1
            rhs = operand()
            node = _binary(op, node, rhs)
        return node

    def expr(self) -> Node:
        return self.binary_chain(("+", "-"), self.term)

    def term(self) -> Node:
        return self.binary_chain(("*", "/", "%"), self.factor)

    def factor(self) -> Node:
        return self.binary_chain(("^",), self.power)  # left to right, as TinyExpr's default

    def power(self) -> Node:
        sign = 1
        while self.is_op("+", "-"):
            sign = -sign if self.tok.text == "-" else sign
            self.k += 1
        node = self.base()
        if sign == 1:
            return node
        return lambda env: -node(env)

    def base(self) -> Node:
        tok = self.tok
        if tok.kind == "number":
            self.k += 1
            value = np.float64(float(tok.text))
            return lambda env: value
        if tok.kind == "name":
            return self.name()
        if self.is_op("("):
            self.k += 1
            node = self.expr()
            if self.is_op(","):
                raise self.error(
                    "a ',' outside a function's arguments (TinyExpr's list) is refused"
                )
            if not self.is_op(")"):
                raise self.error("expected ')'")
            self.k += 1
            return node
        raise self.error("expected a number, a name or '('")

    def name(self) -> Node:
        tok = self.tok
        name = tok.text
        if name in VARIABLES:
            self.k += 1
            self.variables.add(name)
            return lambda env: env[name]
        if name in _REFUSED:
            raise self.error(f"the function {name!r} is not supported")
        if name not in _FUNCTIONS:
            known = ", ".join(sorted(_FUNCTIONS))
            raise ExpressionError(
                f"expression {self.text!r}: unknown name {name!r} at character {tok.pos + 1} "
                f"(variables: x, y, z, t; functions and constants: {known})"
            )
        arity, f = _FUNCTIONS[name]
        self.k += 1
        if arity == 0:
            if self.is_op("("):
                self.k += 1
                if not self.is_op(")"):
                    raise self.error(f"expected ')' ({name} takes no argument)")
                self.k += 1
            value = f()
            return lambda env: value
        if arity == 1:
            arg = self.power()  # TinyExpr: a one-argument function takes the next power
            return lambda env: _function(name, f, env)(arg(env))
        if not self.is_op("("):
            raise self.error(f"expected '(' after {name} (it takes {arity} arguments)")
        args = []
        while True:
            self.k += 1
            args.append(self.expr())
            if not self.is_op(","):
                break
        if not self.is_op(")") or len(args) != arity:
            raise self.error(f"{name} takes {arity} arguments, expected ')' after them")
        self.k += 1
        return lambda env: _function(name, f, env)(*(a(env) for a in args))


class Expression:
    """A parsed PolyFEM expression of x, y, z, t (see the module docstring for the grammar).

    Attributes:
        source: The text as given.
        variables: The variables it uses (a subset of ``x y z t``).
    """

    def __init__(self, source: str, node: Node, variables: frozenset[str]) -> None:
        self.source = source
        self.variables = variables
        self._node = node

    @property
    def depends_on_position(self) -> bool:
        """Whether it uses x, y or z (else it is the same at every point)."""
        return bool(self.variables & {"x", "y", "z"})

    def __call__(
        self,
        x: npt.ArrayLike = 0.0,
        y: npt.ArrayLike = 0.0,
        z: npt.ArrayLike = 0.0,
        t: npt.ArrayLike = 0.0,
    ) -> np.ndarray:
        """The values at the points (x, y, z) and time t, broadcast together (float64).

        Non-finite values (a division by zero, sqrt of a negative number) are returned as
        numpy gives them; the caller decides whether they are an error.
        """
        env = {k: np.asarray(v, dtype=float) for k, v in zip(VARIABLES, (x, y, z, t), strict=True)}
        shape = np.broadcast_shapes(*(v.shape for v in env.values()))
        with np.errstate(all="ignore"):
            value = self._node(env)
        return np.array(np.broadcast_to(np.asarray(value, dtype=float), shape))

    def ufl(self, x: object = 0.0, y: object = 0.0, z: object = 0.0, t: object = 0.0) -> object:
        """The expression as UFL of UFL (or numeric) x, y, z, t, e.g. of the deformed position.

        Raises:
            ExpressionError: A function or operator without a UFL form (``%``, ``floor``,
                ``ceil``, ``compare``, ``smoothstep``, ``half_smoothstep``: not differentiable).
        """
        env = dict(zip(VARIABLES, (x, y, z, t), strict=True))
        env[_UFL] = _ufl_functions()
        return self._node(env)

    def __repr__(self) -> str:
        return f"Expression({self.source!r})"


def parse_expression(text: str) -> Expression:
    """Parse a PolyFEM (TinyExpr) expression of x, y, z, t; no Python code is evaluated.

    Args:
        text: The expression, e.g. ``"0.1 * sin(2 * pi * t) * x"``.

    Returns:
        An :class:`~diffsolids.io.expressions.Expression`, callable as ``expr(x, y, z, t)`` on
        numpy arrays.

    Raises:
        ExpressionError: A syntax error or an unknown name (the message says where).
    """
    if not isinstance(text, str):
        raise ExpressionError(f"expression must be a string, got {text!r}")
    parser = _Parser(text)
    node = parser.parse()
    return Expression(text, node, frozenset(parser.variables))
