"""A job's ``verdict:`` expression: a tiny, safe grammar over the steps' values (no ``eval``).

Grammar (keywords lower case; ``#`` is not a comment)::

    expression := or
    or         := and ("or" and)*
    and        := not ("and" not)*
    not        := "not" not | comparison
    comparison := atom (("<" | "<=" | ">" | ">=" | "==" | "!=") atom)?
    atom       := NUMBER | STRING | "true" | "false" | NAME | NAME "." VALUE
                | ("all" | "any") "(" expression ("," expression)* ")"
                | "(" expression ")"

``NAME`` alone is the step's ``passed``; ``NAME.VALUE`` is one of the values the step declares.
Every value has a type (number, bool, text); the parser checks types against what each step
declares, so ``holes.count and label`` or ``label.text > 3`` are refused at load. At run time a
value that was not measured (None) makes every comparison with it false.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

ValueType = Literal["number", "bool", "text"]
Declared = Mapping[str, Mapping[str, ValueType]]
"""Each step's name -> its values' names -> their types."""
Values = Mapping[str, Mapping[str, Any]]
"""Each step's name -> its values (None where not measured)."""

MAX_LENGTH = 1000
"""Longest expression accepted, in characters (a verdict is a line, not a program)."""
MAX_DEPTH = 32
"""Deepest nesting of parentheses, ``not`` and calls (bounds the parser's recursion)."""

_TOKEN = re.compile(
    r"\s*(?:(?P<number>-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?|-?\.\d+(?:[eE][-+]?\d+)?)"
    r"|(?P<string>\"[^\"]*\"|'[^']*')"
    r"|(?P<name>[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)?)"
    r"|(?P<op><=|>=|==|!=|<|>|\(|\)|,))"
)
_COMPARISONS: dict[str, Callable[[Any, Any], bool]] = {
    "<": lambda a, b: bool(a < b),
    "<=": lambda a, b: bool(a <= b),
    ">": lambda a, b: bool(a > b),
    ">=": lambda a, b: bool(a >= b),
    "==": lambda a, b: bool(a == b),
    "!=": lambda a, b: bool(a != b),
}
_KEYWORDS = ("and", "or", "not", "true", "false", "all", "any")


class ExpressionError(ValueError):
    """An expression that cannot be used; the message names the cause and its column (1-based)."""


@dataclass(frozen=True)
class _Token:
    kind: str  # number, string, name, op, end
    text: str
    column: int


def _tokens(text: str) -> list[_Token]:
    out: list[_Token] = []
    position = 0
    while position < len(text):
        if text[position:].strip() == "":
            break
        match = _TOKEN.match(text, position)
        if match is None or match.end() == position:
            column = position + len(text[position:]) - len(text[position:].lstrip()) + 1
            raise ExpressionError(f"unexpected character {text[column - 1]!r} at column {column}")
        kind = match.lastgroup or "op"
        value = match.group(kind)
        out.append(_Token(kind, value, match.start(kind) + 1))
        position = match.end()
    out.append(_Token("end", "", len(text) + 1))
    return out


# An evaluated node is a function of the values; its type is known at parse time.
Evaluator = Callable[[Values], Any]


@dataclass(frozen=True)
class _Node:
    type: ValueType
    evaluate: Evaluator
    text: str


@dataclass(frozen=True)
class Expression:
    """A parsed verdict: its source text, the ``step.value`` names it reads, and
    :meth:`evaluate`, true or false for a set of step values."""

    text: str
    names: tuple[str, ...]
    _root: _Node

    def evaluate(self, values: Values) -> bool:
        """The verdict for these values (an unmeasured value makes its comparisons false)."""
        return bool(self._root.evaluate(values))


class _Parser:
    def __init__(self, text: str, declared: Declared) -> None:
        self.tokens = _tokens(text)
        self.index = 0
        self.declared = declared
        self.names: list[str] = []
        self.depth = 0

    # ------------------------------------------------------------------ helpers

    @property
    def token(self) -> _Token:
        return self.tokens[self.index]

    def advance(self) -> _Token:
        token = self.token
        self.index += 1
        return token

    def expect(self, text: str) -> None:
        if self.token.text != text or self.token.kind not in ("op", "name"):
            raise ExpressionError(
                f"expected {text!r} at column {self.token.column}, got {self._got()}"
            )
        self.advance()

    def _got(self) -> str:
        return "the end" if self.token.kind == "end" else repr(self.token.text)

    def deeper(self) -> None:
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise ExpressionError(
                f"nested more than {MAX_DEPTH} deep at column {self.token.column}"
            )

    def boolean(self, node: _Node, column: int, what: str) -> None:
        if node.type != "bool":
            raise ExpressionError(
                f"{what} needs a true/false value, but {node.text!r} (column {column}) is a "
                f"{node.type}; compare it, e.g. {node.text} > 0"
            )

    # ------------------------------------------------------------------ grammar

    def parse(self) -> _Node:
        root = self.or_()
        if self.token.kind != "end":
            raise ExpressionError(f"unexpected {self._got()} at column {self.token.column}")
        return root

    def or_(self) -> _Node:
        return self._chain("or", self.and_, any)

    def and_(self) -> _Node:
        return self._chain("and", self.not_, all)

    def _chain(self, word: str, part: Callable[[], _Node], combine: Callable[[Any], bool]) -> _Node:
        column = self.token.column
        first = part()
        parts = [first]
        while self.token.kind == "name" and self.token.text == word:
            self.boolean(parts[-1], column, f"{word!r}")
            self.advance()
            column = self.token.column
            parts.append(part())
            self.boolean(parts[-1], column, f"{word!r}")
        if len(parts) == 1:
            return first
        evaluators = [p.evaluate for p in parts]
        return _Node(
            "bool",
            lambda values: combine(e(values) is True for e in evaluators),
            f" {word} ".join(p.text for p in parts),
        )

    def not_(self) -> _Node:
        if self.token.kind == "name" and self.token.text == "not":
            self.advance()
            self.deeper()
            column = self.token.column
            inner = self.not_()
            self.depth -= 1
            self.boolean(inner, column, "'not'")
            return _Node(
                "bool", lambda values: inner.evaluate(values) is not True, f"not {inner.text}"
            )
        return self.comparison()

    def comparison(self) -> _Node:
        left = self.atom()
        if self.token.kind != "op" or self.token.text not in _COMPARISONS:
            return left
        operator = self.advance()
        right = self.atom()
        ordered = operator.text not in ("==", "!=")
        if ordered and (left.type != "number" or right.type != "number"):
            raise ExpressionError(
                f"{operator.text!r} at column {operator.column} compares numbers, but "
                f"{left.text!r} is a {left.type} and {right.text!r} a {right.type}"
            )
        if left.type != right.type:
            raise ExpressionError(
                f"{operator.text!r} at column {operator.column} compares a {left.type} "
                f"({left.text!r}) with a {right.type} ({right.text!r})"
            )
        compare = _COMPARISONS[operator.text]

        def evaluate(values: Values) -> bool:
            a, b = left.evaluate(values), right.evaluate(values)
            if a is None or b is None:
                return False  # not measured: no comparison holds
            if isinstance(a, float) and math.isnan(a) or isinstance(b, float) and math.isnan(b):
                return False
            return compare(a, b)

        return _Node("bool", evaluate, f"{left.text} {operator.text} {right.text}")

    def atom(self) -> _Node:
        token = self.token
        if token.kind == "number":
            self.advance()
            number = float(token.text)
            return _Node("number", lambda values: number, token.text)
        if token.kind == "string":
            self.advance()
            text = token.text[1:-1]
            return _Node("text", lambda values: text, token.text)
        if token.kind == "op" and token.text == "(":
            self.advance()
            self.deeper()
            inner = self.or_()
            self.depth -= 1
            self.expect(")")
            return _Node(inner.type, inner.evaluate, f"({inner.text})")
        if token.kind == "name":
            if token.text in ("true", "false"):
                self.advance()
                flag = token.text == "true"
                return _Node("bool", lambda values: flag, token.text)
            if token.text in ("all", "any"):
                return self.call()
            if token.text in _KEYWORDS:
                raise ExpressionError(f"unexpected {token.text!r} at column {token.column}")
            self.advance()
            return self.value(token)
        raise ExpressionError(f"expected a value at column {token.column}, got {self._got()}")

    def call(self) -> _Node:
        word = self.advance()
        self.expect("(")
        self.deeper()
        parts: list[_Node] = []
        while True:
            column = self.token.column
            part = self.or_()
            self.boolean(part, column, f"{word.text}()")
            parts.append(part)
            if self.token.text == ",":
                self.advance()
                continue
            break
        self.depth -= 1
        self.expect(")")
        combine = all if word.text == "all" else any
        evaluators = [p.evaluate for p in parts]
        return _Node(
            "bool",
            lambda values: combine(e(values) is True for e in evaluators),
            f"{word.text}({', '.join(p.text for p in parts)})",
        )

    def value(self, token: _Token) -> _Node:
        step, _, key = token.text.partition(".")
        key = key or "passed"
        if step not in self.declared:
            known = ", ".join(self.declared) or "none"
            raise ExpressionError(
                f"unknown step {step!r} at column {token.column} (the steps are: {known})"
            )
        produced = self.declared[step]
        if key not in produced:
            raise ExpressionError(
                f"step {step!r} has no value {key!r} (column {token.column}); it gives: "
                f"{', '.join(produced)}"
            )
        self.names.append(f"{step}.{key}")
        return _Node(produced[key], lambda values: values.get(step, {}).get(key), token.text)


def parse_expression(text: str, declared: Declared) -> Expression:
    """Parse ``text`` against the steps' ``declared`` values; it must be true/false.

    Raises :class:`ExpressionError` naming the cause and column: a syntax error, an unknown
    step or value, a comparison of mismatched types, or a number where true/false is needed.
    """
    if not text.strip():
        raise ExpressionError("the expression is empty")
    if len(text) > MAX_LENGTH:
        raise ExpressionError(f"the expression is {len(text)} characters; at most {MAX_LENGTH}")
    parser = _Parser(text, declared)
    root = parser.parse()
    if root.type != "bool":
        raise ExpressionError(
            f"the verdict must be true or false, but {text.strip()!r} is a {root.type}"
        )
    return Expression(text, tuple(dict.fromkeys(parser.names)), root)


__all__ = ["Declared", "Expression", "ExpressionError", "ValueType", "Values", "parse_expression"]
