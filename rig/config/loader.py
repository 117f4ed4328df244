"""The one configuration loader: YAML with a line for every node, strict pydantic validation.

Every configuration file of the project (recipes, rig profiles, friction-model files)
goes through :func:`read_yaml` and :func:`validate`, so every fault becomes ONE
:class:`ConfigError` whose message names the file, the field path
(``segments[2].slip_after_um``) and the line, and nothing runs from a broken file.

What the reader rejects, beyond YAML syntax:

* duplicate keys (PyYAML silently keeps the last one): the error names both lines;
* nesting deeper than :data:`MAX_DEPTH` (5,000 nested brackets used to raise a
  RecursionError), documents of more than :data:`MAX_NODES` nodes once aliases are
  expanded, and files over :data:`MAX_BYTES`;
* merge keys (``<<``) and tags other than YAML's plain types.

Validation runs pydantic in strict mode on the JSON form of the document: a bool is
no integer (``trials: true``), a string is no number, but an integer is a valid float
and a list a valid tuple. Models derive from :class:`StrictModel` (unknown fields and
non-finite floats are errors).

``extends: other.yaml`` at the top of a file (:func:`read_yaml` with
``allow_extends=True``, used for rig profiles) loads ``other.yaml`` (relative to the
file) and deep-merges this file over it: mappings merge key by key, anything else
(scalars, lists, ``null``) replaces. Every node keeps the file and line it came from.
"""

from __future__ import annotations

import json
import difflib
import os
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError
from pydantic_core import PydanticCustomError

from drivers.config import StrictModel

MAX_DEPTH = 32            # nesting of mappings/sequences; the shipped files use 4
MAX_NODES = 100_000       # nodes after alias expansion (a recipe has a few hundred)
MAX_BYTES = 4_000_000     # file size
MAX_EXTENDS = 8           # length of an ``extends`` chain

M = TypeVar("M", bound=BaseModel)
Loc = tuple  # a path into the document: str keys and int indices


class ConfigError(ValueError):
    """A configuration file cannot be used. ``str()`` names the file, the line and the field."""

    def __init__(self, path: str | os.PathLike, message: str, field: str | None = None,
                 line: int | None = None):
        self.path = str(path)
        self.field = field
        self.line = line
        self.message = message
        where = self.path
        if line is not None:
            where += f", line {line}"
        if field:
            where += f", field '{field}'"
        super().__init__(f"{where}: {message}")


@dataclass(frozen=True)
class Location:
    file: str
    line: int


@dataclass
class YamlDoc:
    """Plain data (dict/list/str/int/float/bool/None) and where each node came from.

    ``where`` maps a path (``("segments", 2, "speed_um_s")``) to the :class:`Location`
    of its key (mapping entries) or of the item (sequence entries); ``()`` is the root.
    """

    data: Any
    where: dict[Loc, Location]
    path: str
    text: str
    chain: list[str] = field(default_factory=list)  # the files merged, base first

    def location(self, loc: Loc) -> Location:
        """Location of ``loc``, or of its deepest parent that exists (a missing field)."""
        loc = tuple(loc)
        while loc not in self.where and loc:
            loc = loc[:-1]
        return self.where.get(loc, Location(self.path, 1))

    def at(self, loc: Loc) -> Any:
        """The data below ``loc``."""
        node = self.data
        for part in loc:
            node = node[part]
        return node


def fmt_loc(loc: Loc) -> str:
    """``("segments", 2, "speed_um_s")`` -> ``segments[2].speed_um_s``."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def parse_loc(text: str) -> Loc:
    """Inverse of :func:`fmt_loc`."""
    out: list = []
    for name, index in re.findall(r"([^.\[\]]+)|\[(\d+)\]", text):
        out.append(int(index) if index else name)
    return tuple(out)


def field_error(field_path: str, message: str) -> PydanticCustomError:
    """An error for a model validator that concerns one field (cross-field checks):
    ``raise field_error("sensors.lvdt.max_um", "must exceed min_um")``. The loader reports
    it at that field's line instead of the model's."""
    return PydanticCustomError("field_check", "{message}", {"message": message, "field_path": field_path})


# ---------------------------------------------------------------------------
# Reading YAML
# ---------------------------------------------------------------------------

class _TooDeep(Exception):
    def __init__(self, mark):
        self.mark = mark


class _Loader(yaml.SafeLoader):
    """PyYAML's composer recurses once per nesting level: count and stop early."""

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent, index):
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH + 1:
                raise _TooDeep(self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


# YAML 1.1 (PyYAML) reads 1e12 and 5e-5 (no dot) as strings; YAML 1.2 and every reader of
# these files mean numbers: resolve them as floats (strict validation would refuse a string).
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))

_PLAIN_TAGS = {"tag:yaml.org,2002:" + t for t in ("str", "int", "float", "bool", "null")}
_TIMESTAMP = "tag:yaml.org,2002:timestamp"
_MAP = "tag:yaml.org,2002:map"
_SEQ = "tag:yaml.org,2002:seq"


def _compose(text: str, path: str, error: type[ConfigError]) -> tuple[yaml.Node | None, _Loader]:
    try:
        loader = _Loader(text)
    except yaml.reader.ReaderError as exc:  # a control character: the reader checks the text first
        line = text[:max(0, exc.position)].count("\n") + 1
        code = ord(exc.character) if isinstance(exc.character, str) else int(exc.character)
        raise error(path, f"character U+{code:04X} is not allowed in YAML (a control character; is this a "
                          "text file?)", line=line) from None
    try:
        return loader.get_single_node(), loader
    except _TooDeep as exc:
        raise error(path, f"nested deeper than {MAX_DEPTH} levels (a configuration file needs a few)",
                    line=exc.mark.line + 1) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else None
        raise error(path, f"YAML syntax error: {exc.problem or exc}", line=line) from None
    except yaml.YAMLError as exc:
        raise error(path, f"YAML error: {exc}") from None
    finally:
        loader.dispose()


def _to_data(root: yaml.Node, loader: _Loader, path: str, error: type[ConfigError]) -> tuple[Any, dict]:
    where: dict[Loc, Location] = {(): Location(path, root.start_mark.line + 1)}
    count = 0

    def conv(node: yaml.Node, loc: Loc, depth: int) -> Any:
        nonlocal count
        count += 1
        line = node.start_mark.line + 1
        if count > MAX_NODES:
            raise error(path, f"more than {MAX_NODES} YAML nodes (aliases expanded)", fmt_loc(loc) or None, line)
        if depth > MAX_DEPTH:  # recursive aliases
            raise error(path, f"nested deeper than {MAX_DEPTH} levels", fmt_loc(loc) or None, line)
        if isinstance(node, yaml.MappingNode):
            if node.tag != _MAP:
                raise error(path, f"unsupported YAML tag {node.tag}", fmt_loc(loc) or None, line)
            out: dict = {}
            key_line: dict[str, int] = {}
            for k, v in node.value:
                kline = k.start_mark.line + 1
                if not isinstance(k, yaml.ScalarNode):
                    raise error(path, "a mapping key must be a plain name", fmt_loc(loc) or None, kline)
                if k.tag == "tag:yaml.org,2002:merge":
                    raise error(path, "YAML merge keys ('<<') are not supported; write the fields out "
                                      "(rig profiles may use 'extends: other.yaml')", fmt_loc(loc) or None, kline)
                key = str(k.value)
                if key in out:
                    raise error(path, f"duplicate key '{key}' (first at line {key_line[key]}, again at line "
                                      f"{kline}); YAML would silently keep the last one",
                                fmt_loc(loc + (key,)), kline)
                key_line[key] = kline
                where[loc + (key,)] = Location(path, kline)
                out[key] = conv(v, loc + (key,), depth + 1)
            return out
        if isinstance(node, yaml.SequenceNode):
            if node.tag != _SEQ:
                raise error(path, f"unsupported YAML tag {node.tag}", fmt_loc(loc) or None, line)
            items = []
            for i, item in enumerate(node.value):
                where[loc + (i,)] = Location(path, item.start_mark.line + 1)
                items.append(conv(item, loc + (i,), depth + 1))
            return items
        if node.tag == _TIMESTAMP:
            return str(node.value)  # a date-like string stays a string
        if node.tag not in _PLAIN_TAGS:
            raise error(path, f"unsupported YAML tag {node.tag}", fmt_loc(loc) or None, line)
        try:
            return loader.construct_object(node, deep=True)
        except yaml.YAMLError as exc:
            raise error(path, f"bad YAML value: {exc}", fmt_loc(loc) or None, line) from None

    return conv(root, (), 0), where


def _read_text(path: Path, error: type[ConfigError]) -> str:
    try:
        size = path.stat().st_size
        if size > MAX_BYTES:
            raise error(path, f"file of {size} bytes; a configuration file is under {MAX_BYTES} bytes")
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(path, "no such file") from None
    except IsADirectoryError:
        raise error(path, "is a directory, not a YAML file") from None
    except UnicodeDecodeError as exc:
        raise error(path, f"not valid UTF-8 text ({exc.reason})") from None
    except OSError as exc:
        raise error(path, f"cannot read: {exc.strerror or exc}") from None


def parse_yaml(text: str, path: str | os.PathLike = "<yaml>", *, error: type[ConfigError] = ConfigError,
               what: str = "a YAML mapping") -> YamlDoc:
    """Parse YAML ``text`` into a :class:`YamlDoc` whose root is a mapping."""
    path = str(path)
    root, loader = _compose(text, path, error)
    if root is None:
        raise error(path, f"empty file (expected {what})", line=1)
    data, where = _to_data(root, loader, path, error)
    if not isinstance(data, dict):
        raise error(path, f"expected {what}, found a {type(data).__name__}", line=root.start_mark.line + 1)
    return YamlDoc(data, where, path, text, [path])


def read_yaml(path: str | os.PathLike, *, error: type[ConfigError] = ConfigError, what: str = "a YAML mapping",
              allow_extends: bool = False, _seen: tuple = ()) -> YamlDoc:
    """Read a YAML file (see :func:`parse_yaml`); resolve ``extends`` when ``allow_extends``."""
    p = Path(path)
    text = _read_text(p, error)
    doc = parse_yaml(text, p, error=error, what=what)
    if not allow_extends or "extends" not in doc.data:
        return doc
    base_name = doc.data.pop("extends")
    at = doc.where.pop(("extends",))
    if not isinstance(base_name, str) or not base_name:
        raise error(p, "extends: expected the path of a YAML file", "extends", at.line)
    base_path = Path(base_name) if Path(base_name).is_absolute() else p.parent / base_name
    key = str(base_path.resolve())
    if key in _seen or key == str(p.resolve()):
        raise error(p, f"extends: {base_name} extends this file again (a cycle)", "extends", at.line)
    if len(_seen) >= MAX_EXTENDS:
        raise error(p, f"extends: a chain of more than {MAX_EXTENDS} files", "extends", at.line)
    if not base_path.is_file():
        raise error(p, f"extends: no such file {base_path}", "extends", at.line)
    base = read_yaml(base_path, error=error, what=what, allow_extends=True, _seen=_seen + (str(p.resolve()),))
    return _merge(base, doc)


def _merge(base: YamlDoc, over: YamlDoc) -> YamlDoc:
    where = dict(base.where)

    def merge(b: Any, o: Any, loc: Loc) -> Any:
        if isinstance(b, dict) and isinstance(o, dict):
            out = dict(b)
            for k, v in o.items():
                out[k] = merge(b[k], v, loc + (k,)) if k in b else _replace(v, loc + (k,))
            return out
        return _replace(o, loc)

    def _replace(o: Any, loc: Loc) -> Any:
        n = len(loc)
        for k in [k for k in where if k[:n] == loc and len(k) > n]:
            del where[k]
        return o

    data = merge(base.data, over.data, ())
    for k, v in over.where.items():
        if k != ():
            where[k] = v
    where[()] = over.where[()]
    return YamlDoc(data, where, over.path, over.text, base.chain + [over.path])


# ---------------------------------------------------------------------------
# Validation with errors mapped back to file and line
# ---------------------------------------------------------------------------

def _clean_loc(data: Any, loc: Loc, missing: bool) -> Loc:
    """Walk a pydantic error ``loc`` along the data: drop union tags and validator names."""
    out: list = []
    node = data
    for i, part in enumerate(loc):
        last = i == len(loc) - 1
        if isinstance(node, dict):
            if isinstance(part, str) and part in node:
                out.append(part)
                node = node[part]
            elif missing and last:
                out.append(part)
                node = None
            # else: a union tag ('velocity_steps') or 'function-after[...]': not in the file
        elif isinstance(node, list):
            if isinstance(part, int) and 0 <= part < len(node):
                out.append(part)
                node = node[part]
        else:
            break
    return tuple(out)


def _members(t: Any) -> list:
    """The types a field annotation can hold: Annotated and Optional/Union unwrapped."""
    origin = typing.get_origin(t)
    if origin is typing.Annotated:
        return _members(typing.get_args(t)[0])
    if origin in (typing.Union, types.UnionType):
        return [m for a in typing.get_args(t) for m in _members(a)]
    return [t]


def _step(t: Any, part: Any) -> list:
    """The types one part of a pydantic error's ``loc`` leads to from type ``t``: a model's field, a
    list's item, a mapping's value, or (a union tag) the member whose ``kind`` is that tag."""
    out = []
    for m in _members(t):
        origin, args = typing.get_origin(m), typing.get_args(m)
        if isinstance(m, type) and issubclass(m, BaseModel):
            if isinstance(part, str) and part in m.model_fields:
                out.append(m.model_fields[part].annotation)
            kind = m.model_fields.get("kind")
            if kind is not None and part in typing.get_args(kind.annotation):
                out.append(m)
        elif origin in (list, tuple) and isinstance(part, int) and args:
            out.append(args[0])
        elif origin is dict and isinstance(part, str) and len(args) == 2:
            out.append(args[1])
    return out


def _known_fields(model: type[BaseModel], loc: Loc) -> list[str]:
    """The field names of the model that the pydantic error location ``loc`` (its last part, the
    unknown key, left out) points into; [] when it cannot be told."""
    types_ = [model]
    for part in loc[:-1]:
        types_ = [n for t in types_ for n in _step(t, part)]
    for t in types_:
        for m in _members(t):
            if isinstance(m, type) and issubclass(m, BaseModel):
                return list(m.model_fields)
    return []


def _did_you_mean(word: Any, choices) -> str:
    """``; did you mean 'x'?`` for the closest of ``choices`` to ``word`` (difflib), else ''."""
    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def _describe(err: dict, model: type[BaseModel] | None = None) -> str:
    typ = err["type"]
    if typ == "missing":
        return "required field is missing"
    if typ == "extra_forbidden":
        hint = _did_you_mean(err["loc"][-1], _known_fields(model, tuple(err["loc"]))) if model else ""
        return "unknown field (check the spelling and the unit in the name)" + hint
    msg = err["msg"]
    if typ == "union_tag_invalid":
        ctx = err.get("ctx") or {}
        msg += _did_you_mean(ctx.get("tag", ""), re.findall(r"'([^']*)'", str(ctx.get("expected_tags", ""))))
    if typ == "field_check":
        return msg
    if "input" in err and typ != "union_tag_invalid" and not isinstance(err["input"], (dict, list)):
        msg += f" (got {err['input']!r})"
    return msg


def validate(model: type[M], doc: YamlDoc, *, root: Loc = (), error: type[ConfigError] = ConfigError) -> M:
    """Validate the data at ``root`` of ``doc`` strictly (JSON mode) against ``model``.

    Raises ONE ``error`` naming the file, the field path and the line of the first
    problem (and lists up to three more)."""
    data = doc.at(root)
    try:
        payload = json.dumps(data, allow_nan=True)
    except (TypeError, ValueError) as exc:  # pragma: no cover - _to_data yields JSON types only
        raise error(doc.path, f"cannot represent the document: {exc}") from None
    try:
        return model.model_validate_json(payload, strict=True)
    except ValidationError as exc:
        errors = exc.errors(include_url=False)

        def place(e: dict) -> tuple[Loc, Location]:
            fp = (e.get("ctx") or {}).get("field_path")
            if fp:
                loc = tuple(root) + parse_loc(fp)
            else:
                loc = tuple(root) + _clean_loc(data, tuple(e["loc"]), e["type"] == "missing")
            return loc, doc.location(loc)

        loc, at = place(errors[0])
        msg = _describe(errors[0], model)
        if len(errors) > 1:
            others = []
            for e in errors[1:4]:
                l2, at2 = place(e)
                others.append(f"{fmt_loc(l2) or '<top level>'} (line {at2.line}): {_describe(e, model)}")
            msg += "; also: " + "; ".join(others)
            if len(errors) > 4:
                msg += f"; and {len(errors) - 4} more"
        if at.file != doc.path:
            msg += f" (extended by {doc.path})"
        raise error(at.file, msg, field=fmt_loc(loc) or None, line=at.line) from None


#: top-level keys that say what kind of configuration file a mapping is
_KINDS = (("a recipe", {"segments"}), ("a rig profile", {"actuator", "controller", "stroke", "servovalve"}),
          ("a friction model", {"friction_model", "baseline", "extensions"}))


def kind_of(data: Any, but: set[str] = frozenset()) -> str | None:
    """'a recipe', 'a rig profile' or None: what a YAML mapping looks like, from its top-level keys
    (keys in ``but``, the fields of the expected model, say nothing)."""
    if not isinstance(data, dict):
        return None
    for name, keys in _KINDS:
        if (keys - set(but)) & set(data):
            return name
    return None


def expect_kind(doc: YamlDoc, model: type, what: str, error: type[ConfigError] = ConfigError) -> None:
    """One clear error when ``doc`` is plainly another kind of file (a recipe given as a profile, ...)."""
    other = kind_of(doc.data, but=set(getattr(model, "model_fields", {})))
    if other is not None and other != what:
        raise error(doc.path, f"this is {other}, not {what}", line=1)


def load_model_yaml(path: str | os.PathLike, model: type[M], *, key: str | None = None,
                    error: type[ConfigError] = ConfigError, what: str | None = None) -> M:
    """Read and validate a model file (e.g. a friction model) with the pydantic class ``model``.

    ``key``: an optional top-level wrapper (``friction_model:``) around the fields.
    ``what``: the file's kind in messages (default the class name). A recipe or a
    rig profile given instead is one clear error ("this is a recipe, not a ...").
    """
    what = what or model.__name__
    doc = read_yaml(path, error=error, what=f"a {what} mapping")
    other = kind_of(doc.data, but=set(getattr(model, "model_fields", {})))
    if other is not None and (key is None or key not in doc.data):
        raise error(doc.path, f"this is {other}, not a {what}", line=1)
    root: Loc = ()
    if key is not None and set(doc.data) == {key}:
        if not isinstance(doc.data[key], dict):
            raise error(doc.path, f"expected a {what} mapping", key, doc.location((key,)).line)
        root = (key,)
    return validate(model, doc, root=root, error=error)


__all__ = ["ConfigError", "StrictModel", "Location", "YamlDoc", "read_yaml", "parse_yaml", "validate",
           "load_model_yaml", "kind_of", "expect_kind", "field_error", "fmt_loc", "parse_loc", "MAX_DEPTH", "MAX_NODES"]
