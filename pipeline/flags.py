"""Command-line flags generated from config dataclasses: one flag per field, the field's default as
the flag's and the field's docstring (the string literal right after it) as its help.

The fields are read from the class's source with ``ast``, so building a parser imports none of the
modules that define the configs (torch, numpy): ``mushroom-pose --help`` stays fast, and a Ctrl-C
never lands inside a C extension's import. ``config_from_args`` builds the real dataclass once the
command runs.
"""

from __future__ import annotations

import argparse
import ast
import functools
import importlib.util
import re
from pathlib import Path

NO_DEFAULT = object()
"""The default of a field that has none, or one that is not a literal (a ``default_factory``)."""


class ConfigField:
    """One field of a config dataclass as its source states it."""

    __slots__ = ("name", "annotation", "default", "doc")

    def __init__(self, name: str, annotation: ast.expr, default, doc: str):
        self.name, self.annotation, self.default, self.doc = name, annotation, default, doc


FLAG_KEYS = frozenset({"name", "parse", "metavar", "help"})
"""What a field's entry in ``add_config_flags``'s ``flags`` may set: ``name``, the flag without its
dashes; ``parse``, a validator (one word in, a value out, or argparse.ArgumentTypeError); ``metavar``;
and ``help``, for a field its class leaves undocumented."""


@functools.cache
def config_fields(reference: str) -> tuple[ConfigField, ...]:
    """The fields of the dataclass ``reference`` ("package.module:Class"), read from its module's
    source without importing that module."""
    module, _, name = reference.partition(":")
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        raise LookupError(f"{reference}: no source for {module}")
    body = _class_body(Path(spec.origin).read_text(), name)
    if body is None:
        raise LookupError(f"{reference}: no class {name} in {spec.origin}")
    fields = []
    for statement, following in zip(body, [*body[1:], None]):
        if not (isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name)):
            continue
        doc = following.value.value if (isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)
                                        and isinstance(following.value.value, str)) else ""
        fields.append(ConfigField(statement.target.id, _without_aliases(statement.annotation, module),
                                  _literal_default(statement.value), " ".join(doc.split())))
    return tuple(fields)


def _without_aliases(annotation: ast.expr, module: str) -> ast.expr:
    """``annotation`` with each name of a module-level type alias (``Method = Literal[...]``, in
    ``module`` or imported into it) replaced by what the alias stands for, so that a set of choices is
    written once and every config that takes it gets its flag's choices."""
    class Resolve(ast.NodeTransformer):
        def visit_Name(self, node: ast.Name) -> ast.expr:
            if node.id in _SCALARS or node.id in ("Literal", "tuple", "None"):
                return node
            return _alias(module, node.id) or node

    return Resolve().visit(annotation)


@functools.cache
def _module_statements(module: str) -> tuple[ast.stmt, ...]:
    """The top-level statements of ``module``'s source (empty when it has none)."""
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
        return ()
    return tuple(ast.parse(Path(spec.origin).read_text()).body)


def _alias(module: str, name: str, depth: int = 0) -> ast.expr | None:
    """What the type alias ``name`` of ``module`` stands for, followed through ``from X import name``."""
    for statement in _module_statements(module):
        if (isinstance(statement, ast.Assign) and len(statement.targets) == 1
                and isinstance(statement.targets[0], ast.Name) and statement.targets[0].id == name
                and isinstance(statement.value, ast.Subscript)):
            return statement.value
        if isinstance(statement, ast.ImportFrom) and statement.module and depth < 3:
            if any((alias.asname or alias.name) == name for alias in statement.names):
                return _alias(statement.module, name, depth + 1)
    return None


def _class_body(source: str, name: str) -> list[ast.stmt] | None:
    """The statements of the module-level class ``name`` in ``source``. Parses the class alone (up to
    the next line that starts in column 0), a fraction of the module's time, and the whole module
    where that is not the class whole (a string continued in column 0)."""
    block = re.search(rf"^class {name}\b.*?(?=^\S|\Z)", source, re.MULTILINE | re.DOTALL)
    if block is None:
        return None
    try:
        return ast.parse(block.group()).body[0].body
    except SyntaxError:
        return next((node.body for node in ast.parse(source).body
                     if isinstance(node, ast.ClassDef) and node.name == name), None)


def _literal_default(value: ast.expr | None):
    """The default a field's assignment gives, when it is a literal (also inside ``field(default=...)``)."""
    if isinstance(value, ast.Call) and getattr(value.func, "id", None) == "field":
        value = next((keyword.value for keyword in value.keywords if keyword.arg == "default"), None)
    if value is None:
        return NO_DEFAULT
    try:
        return ast.literal_eval(value)
    except ValueError:
        return NO_DEFAULT


_SCALARS = {"int": int, "float": float, "str": str, "bool": bool}


def _flag_type(annotation: ast.expr, where: str) -> tuple[type, int | str | None, tuple | None]:
    """(type of each value, nargs, choices) for a field annotated ``annotation``: int, float, str or
    bool, ``X | None``, ``tuple[X, ...]``, ``tuple[X, X]`` or ``Literal[...]``."""
    if isinstance(annotation, ast.Name) and annotation.id in _SCALARS:
        return _SCALARS[annotation.id], None, None
    if isinstance(annotation, ast.BinOp) and isinstance(annotation.op, ast.BitOr):
        sides = [annotation.left, annotation.right]
        others = [side for side in sides if not (isinstance(side, ast.Constant) and side.value is None)]
        if len(others) == 1:
            return _flag_type(others[0], where)
    if isinstance(annotation, ast.Subscript) and isinstance(annotation.value, ast.Name):
        items = annotation.slice.elts if isinstance(annotation.slice, ast.Tuple) else [annotation.slice]
        if annotation.value.id == "Literal" and items and all(isinstance(i, ast.Constant) for i in items):
            choices = tuple(item.value for item in items)
            return type(choices[0]), None, choices
        if annotation.value.id == "tuple" and items:
            if len(items) == 2 and isinstance(items[1], ast.Constant) and items[1].value is Ellipsis:
                return _flag_type(items[0], where)[0], "+", None
            kinds = {_flag_type(item, where)[0] for item in items}
            if len(kinds) == 1:
                return kinds.pop(), len(items), None
    raise TypeError(f"{where}: no flag for a field of type {ast.unparse(annotation)}; exclude it")


def _shown(value) -> str:
    """A default as it is typed on the command line."""
    if isinstance(value, (tuple, list)):
        return " ".join(map(_shown, value))
    return f"{value:g}" if isinstance(value, float) else str(value)


def _help(text: str, default, flag_name: str, flag_names: dict[str, str]) -> str:
    """``text`` with ``field`` marks turned into the field's flag (or plain names) and the default
    appended, escaped for argparse's %-formatting."""
    text = re.sub(r"``([^`]+)``", lambda mark: flag_names.get(mark[1], mark[1]), text)
    if default is True or default is False:
        shown = f"--{'' if default else 'no-'}{flag_name}"
    else:
        shown = None if default is None or default is NO_DEFAULT else _shown(default)
    return (text + (f" (default: {shown})" if shown is not None else "")).strip().replace("%", "%%")


def add_config_flags(parser: argparse.ArgumentParser, reference: str, flags: dict[str, dict] | None = None,
                     exclude: tuple[str, ...] = (), only: tuple[str, ...] | None = None, prefix: str = "") -> None:
    """One flag per field of the dataclass ``reference`` ("package.module:Class") on ``parser``, bar
    ``exclude`` (or only ``only``): ``--prefix-field-name`` unless its entry in ``flags`` (FLAG_KEYS)
    names it, its value in ``args.<prefix><field>``, its default the field's, its help the field's
    docstring. A bool field becomes ``--x/--no-x``."""
    flags = flags or {}
    for field, options in flags.items():
        if not options.keys() <= FLAG_KEYS:
            raise TypeError(f"{reference}.{field}: unknown flag options {sorted(options.keys() - FLAG_KEYS)}")
    fields = [field for field in config_fields(reference)
              if field.name not in exclude and (only is None or field.name in only)]
    names = {field.name: flags.get(field.name, {}).get("name") or (prefix + field.name).replace("_", "-")
             for field in fields}
    marks = {field: f"--{name}" for field, name in names.items()}
    for field in fields:
        options, name = flags.get(field.name, {}), names[field.name]
        value_type, nargs, choices = _flag_type(field.annotation, f"{reference}.{field.name}")
        if field.default is NO_DEFAULT:
            raise TypeError(f"{reference}.{field.name}: no literal default to give its flag; exclude it")
        common = {"dest": prefix + field.name, "default": field.default,
                  "help": _help(options.get("help") or field.doc, field.default, name, marks)}
        if value_type is bool:
            parser.add_argument(f"--{name}", action=argparse.BooleanOptionalAction, **common)
        else:
            metavar = options.get("metavar") or (None if choices else name.replace("-", "_").upper())
            parser.add_argument(f"--{name}", type=options.get("parse") or value_type, nargs=nargs, choices=choices,
                                metavar=metavar, **common)


def config_from_args(config_class, args: argparse.Namespace, prefix: str = "", **overrides):
    """``config_class`` with the values of the flags ``add_config_flags`` gave it (same ``prefix``),
    then ``overrides``; a field without a flag keeps its default. Lists from ``nargs`` become tuples."""
    import dataclasses

    values = {}
    for field in dataclasses.fields(config_class):
        if hasattr(args, prefix + field.name):
            value = getattr(args, prefix + field.name)
            values[field.name] = tuple(value) if isinstance(value, list) else value
    return config_class(**{**values, **overrides})
