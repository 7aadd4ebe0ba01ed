"""Reading a config: YAML with duplicate keys refused, ``${VAR}`` from the
environment, and every problem found at once."""

from __future__ import annotations

import contextlib
import logging
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from pydantic import (
    ValidationError,
)

from ..errors import ConfigError
from .checks import cross_problems
from .fields import show, yaml_path
from .problems import pydantic_problem, salvage
from .schema import GatewayConfig

log = logging.getLogger("imu_gateway.config")

_ENV_REF = re.compile(r"\$\$\{|\$\{([^}]*)\}|\$\{")
_ENV_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")

# ------------------------------------------------------------------------- loading


def _expand_env(
    node: Any, loc: tuple[int | str, ...], env: Mapping[str, str],
    problems: list[str], unresolved: set[str],
) -> Any:
    """``${NAME}`` in every string value replaced from ``env``; ``$${`` is a literal ``${``."""
    if isinstance(node, dict):
        return {k: _expand_env(v, (*loc, str(k)), env, problems, unresolved)
                for k, v in node.items()}
    if isinstance(node, list):
        return [_expand_env(v, (*loc, i), env, problems, unresolved)
                for i, v in enumerate(node)]
    if not isinstance(node, str) or "${" not in node:
        return node
    path = yaml_path(loc)
    out: list[str] = []
    pos = 0
    ok = True
    for match in _ENV_REF.finditer(node):
        out.append(node[pos:match.start()])
        pos = match.end()
        name = match.group(1)
        if match.group(0) == "$${":
            out.append("${")
        elif name is None:
            problems.append(f"{path}: unterminated ${{ (write $${{ for a literal ${{)")
            ok = False
        elif not _ENV_NAME.fullmatch(name):
            problems.append(f"{path}: {show('${' + name + '}')} is not an environment "
                            "variable reference (a name is letters, digits and _)")
            ok = False
        elif name not in env:
            problems.append(f"{path}: environment variable {name} is not set")
            ok = False
        else:
            out.append(env[name])
    out.append(node[pos:])
    if not ok:
        unresolved.add(path)
        return node
    return "".join(out)


def config_from_dict(
    data: Mapping[str, Any], env: Mapping[str, str] | None = None
) -> GatewayConfig:
    """Validate already-parsed config data (``${NAME}`` expanded from ``env``,
    default ``os.environ``).  Raises :class:`ConfigError` with every problem."""
    problems: list[str] = []
    unresolved: set[str] = set()
    expanded = _expand_env(dict(data), (), os.environ if env is None else env,
                           problems, unresolved)
    try:
        config = GatewayConfig.model_validate(expanded)
    except ValidationError as exc:
        for error in exc.errors():
            if yaml_path(error["loc"]) not in unresolved:
                problems.append(pydantic_problem(error))
        # Best effort on a config already known to be bad: never let it hide those problems.
        with contextlib.suppress(Exception):
            problems += cross_problems(salvage(expanded))
    except ConfigError as exc:
        problems += exc.problems
    else:
        if not problems:
            return config
    raise ConfigError(problems)


class _Loader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping (PyYAML keeps the last)."""


def _construct_mapping(loader: _Loader, node: yaml.MappingNode) -> dict[Any, Any]:
    seen: dict[Any, tuple[int, int]] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node)
        at = (key_node.start_mark.line, key_node.start_mark.column)
        try:
            first = seen.setdefault(key, at)
        except TypeError:  # an unhashable key: SafeLoader reports it
            continue
        if first != at:  # (by place, not line: ``{port: 1, port: 2}`` is one line)
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {show(key)} (first given on line {first[0] + 1})",
                key_node.start_mark,
            )
    return loader.construct_mapping(node)


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def _kind(value: object) -> str:
    if isinstance(value, list):
        return "a list"
    if isinstance(value, bool):
        return "true/false"
    if isinstance(value, str):
        return "a string"
    return "a number" if isinstance(value, int | float) else f"a {type(value).__name__}"


def load_config_text(
    text: str, source: str = "<config>", env: Mapping[str, str] | None = None
) -> GatewayConfig:
    """Parse and validate YAML text; ``source`` names it in file-level problems."""
    return config_from_dict(parse_text(text, source), env)


def load_config(path: str | os.PathLike[str], env: Mapping[str, str] | None = None
                ) -> GatewayConfig:
    """Read, parse and validate a config file.  Raises :class:`ConfigError`, never
    anything else for a bad or missing file."""
    source = os.fspath(path)
    reasons: dict[type[OSError], str] = {
        FileNotFoundError: "no such file",
        IsADirectoryError: "is a directory, not a config file",
        PermissionError: "cannot read: permission denied",
    }
    try:
        raw = Path(source).read_bytes()
    except OSError as exc:
        reason = reasons.get(type(exc)) or f"cannot read: {exc.strerror or exc}"
        raise ConfigError([f"{source}: {reason}"]) from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError([f"{source}: not UTF-8 text (bad byte at offset {exc.start})"]) \
            from None
    return load_config_text(text, source, env)


# ------------------------------------------------------- the file as written: a reload

#: The config's secrets, by YAML path (``*``: any key of a mapping, ``[]``: any item of a
#: list): shown as their ``${VAR}`` reference, or as ``***`` when written literally
#: (``GET /api/v1/config``).  A user's or a token's role stays visible.
SECRET_PATHS = (("mqtt", "password"), ("http", "token"), ("opcua", "users", "*"),
                ("http", "tokens", "[]", "token"), ("http", "users", "*", "password"))
HIDDEN = "***"
_ONLY_REFS = re.compile(r"(?:\$\{[A-Za-z_][A-Za-z0-9_]*\}|\$\$\{|[^$])*")
Place = tuple[Any, Any, tuple[Any, ...]]  # (mapping or list, key or index, its YAML path)


class ConfigSource:
    """The config as written: its file (``None``: given in memory) and its data with
    every ``${VAR}`` unexpanded (what ``GET`` shows, and what a ``PUT`` saves): a
    ruamel CommentedMap as read (comments kept), or plain data.

    A file's text is kept as read and parsed when first asked for: ruamel.yaml and
    the parsed tree took 1.2 MB of a gateway that never shows nor saves its config."""

    def __init__(self, path: Path | None, data: Any = None, *, text: str | None = None) -> None:
        self.path = path
        self._data = data
        self._text = text  # (not parsed yet)

    @property
    def data(self) -> Any:
        if self._text is not None:
            self._data, self._text = _as_written(self._text), None
        return self._data

    @data.setter
    def data(self, data: Any) -> None:
        self._data, self._text = data, None

    @classmethod
    def read(cls, path: str | os.PathLike[str]) -> ConfigSource:
        """The file's text, to be parsed without expanding anything (``load_config``
        has accepted it)."""
        return cls(Path(path), text=Path(path).read_text("utf-8-sig"))


def _as_written(text: str) -> Any:
    """``round_trip_load``, or where ruamel.yaml refuses what the config's own reading
    accepted, that reading's plain data (no comments kept): the config can still be
    shown and saved."""
    from ruamel.yaml.error import YAMLError

    try:
        return round_trip_load(text)
    except YAMLError as exc:
        log.warning("config: its comments will not be kept when it is saved: ruamel.yaml "
                    "cannot read it (%s)", " ".join(str(exc).split()))
        return parse_text(text)


def round_trip_load(text: str) -> Any:
    """YAML with its comments and key order (ruamel.yaml's round trip)."""
    from ruamel.yaml import YAML  # (only a reload needs it)

    return YAML(typ="rt").load(text)


def _secret_places(data: Any, pattern: tuple[str, ...]) -> list[Place]:
    """Where each secret the pattern names is in ``data``: its container, its key (or
    index) there, and its path from the top."""
    places: list[Place] = [(None, None, ())]
    found: list[tuple[Any, tuple[Any, ...]]] = [(data, ())]
    for step in pattern:
        places = []
        for node, path in found:
            if step == "[]" and isinstance(node, list):
                places += [(node, n, (*path, n)) for n in range(len(node))]
            elif step != "[]" and isinstance(node, Mapping):
                keys = list(node) if step == "*" else [step] if step in node else []
                places += [(node, k, (*path, k)) for k in keys]
        found = [(c[k], path) for c, k, path in places]
    return places


def _at(data: Any, path: tuple[Any, ...]) -> Any:
    """The value at ``path`` in ``data`` (``None``: nothing there)."""
    for step in path:
        in_mapping = isinstance(data, Mapping) and step in data
        if in_mapping or (isinstance(data, list) and isinstance(step, int)
                          and step < len(data)):
            data = data[step]
        else:
            return None
    return data


def shown(data: Any) -> Any:
    """A copy of the config's data with every secret hidden: a value that is only
    ``${VAR}`` references stays as written; a literal one becomes ``***``."""
    copy = copy_plain(data)
    for pattern in SECRET_PATHS:
        for container, key, _ in _secret_places(copy, pattern):
            value = container[key]
            if not (isinstance(value, str) and "${" in value
                    and _ONLY_REFS.fullmatch(value) and _no_literal(value)):
                container[key] = None if value is None else HIDDEN
    return copy


def _no_literal(value: str) -> bool:
    """Nothing but references: ``${A}`` or ``${A}${B}``, no secret text beside them."""
    return not re.sub(r"\$\{[A-Za-z_][A-Za-z0-9_]*\}", "", value)


def with_secrets_kept(new: Any, old: Any) -> Any:
    """``new`` (a PUT's data) where each secret sent back as ``***`` takes the value at
    the same place of ``old`` (the config as written): a client that read a hidden
    secret can send the whole config back without knowing it.  A ``***`` in a list
    (``http.tokens``) is kept only where the entry around it is the one that was there
    (the same role): a list reordered around it would otherwise give a token another
    role.  Raises ``ConfigError`` for a ``***`` with nothing, or something else, there."""
    merged = copy_plain(new)
    problems = []
    for pattern in SECRET_PATHS:
        for container, key, path in _secret_places(merged, pattern):
            if container[key] != HIDDEN:
                continue
            previous, entry = _at(old, path), path[:-1]
            same_entry = "[]" not in pattern or _without(_at(old, entry), key) == \
                _without(_at(merged, entry), key)
            if previous is None or previous == HIDDEN or not same_entry:
                problems.append(f"{yaml_path(tuple(path))}: \"***\" stands for the secret "
                                "that was at this place, and none (or another entry) is there "
                                "now: give the secret itself, or its ${VAR}")
            else:
                container[key] = previous
    if problems:
        raise ConfigError(problems)
    return merged


def _without(entry: Any, key: Any) -> Any:
    """A list entry without its secret (what must be equal for ``***`` to be kept)."""
    return {k: v for k, v in entry.items() if k != key} if isinstance(entry, Mapping) \
        else entry


def copy_plain(data: Any) -> Any:
    """Plain dicts and lists (no comments), deep."""
    if isinstance(data, Mapping):
        return {k: copy_plain(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [copy_plain(v) for v in data]
    return data


def merged_into(tree: Any, data: Any) -> Any:
    """``data`` written into ``tree`` (a ruamel mapping read from the file) in place:
    keys kept keep their place and comments, new ones go at the end, removed ones
    go; list items are matched by position.  Returns what to dump."""
    if isinstance(tree, dict) and isinstance(data, Mapping):
        for key in [k for k in tree if k not in data]:
            del tree[key]
        for key, value in data.items():
            tree[key] = merged_into(tree[key], value) if key in tree else value
        return tree
    if isinstance(tree, list) and isinstance(data, list):
        for i, value in enumerate(data):
            if i < len(tree):
                tree[i] = merged_into(tree[i], value)
            else:
                tree.append(value)
        del tree[len(data):]
        return tree
    return data


def save_atomically(path: Path, data: Any) -> None:
    """``data`` written over ``path`` with the comments of what is there: a temporary
    file beside it, fsync'd, then renamed; the previous file kept as ``<name>.bak``.
    Raises ``OSError`` (a read-only file or folder)."""
    from ruamel.yaml import YAML

    text = path.read_text("utf-8-sig")
    tree = merged_into(round_trip_load(text), data)
    if not os.access(path, os.W_OK):  # (renaming over it would still work in its folder)
        raise PermissionError(13, "the file is read-only", str(path))
    temp = path.with_name(f".{path.name}.new")
    yaml_rt = YAML(typ="rt")
    yaml_rt.preserve_quotes = True
    yaml_rt.indent(**indentation_of(text))
    with open(temp, "w", encoding="utf-8") as out:
        yaml_rt.dump(tree, out)
        out.flush()
        os.fsync(out.fileno())
    try:
        os.chmod(temp, path.stat().st_mode & 0o777)
        backup = path.with_name(path.name + ".bak")
        with contextlib.suppress(FileNotFoundError):
            backup.unlink()
        os.link(path, backup)
        os.replace(temp, path)
    except OSError:
        with contextlib.suppress(OSError):
            temp.unlink()
        raise
    _fsync_dir(path.parent)


#: a top-level key alone on its line, then (past blank and comment lines) its first key
_NESTED_KEY = re.compile(r"^[^\s#-][^\n]*:[ \t]*(?:#[^\n]*)?\n"
                         r"((?:[ \t]*(?:#[^\n]*)?\n)*)( +)[^\s#-]", re.MULTILINE)


def indentation_of(text: str) -> dict[str, int]:
    """The file's own indentation, for ruamel's ``indent()``, so that a save changes only
    what changed: a mapping's (``mqtt:`` then ``  url:``), and a list's (``buses:`` then
    ``  - name:``: the dash 2 in, its entries 4).  ruamel's default puts the dash at its
    parent's column, which made every list of a saved file move."""
    from ruamel.yaml.util import load_yaml_guess_indent

    nested = _NESTED_KEY.search(text)
    mapping = len(nested.group(2)) if nested else 2
    _, sequence, offset = load_yaml_guess_indent(text)
    if sequence is None or offset is None:
        return {"mapping": mapping, "sequence": mapping, "offset": 0}
    return {"mapping": mapping, "sequence": sequence, "offset": offset}


def _fsync_dir(folder: Path) -> None:
    """The rename itself made durable (where the system allows a folder's fsync)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def parse_text(text: str, source: str = "<config>") -> dict[str, Any]:
    """YAML (or JSON, a subset) to a mapping, unexpanded.  Raises ``ConfigError``."""
    try:
        data = yaml.load(text, Loader=_Loader)  # a SafeLoader subclass
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"{source}:{mark.line + 1}:{mark.column + 1}" if mark else source
        what = " ".join(str(exc.problem or exc.context or "syntax error").split())
        raise ConfigError([f"{where}: invalid YAML: {what}"]) from None
    except yaml.YAMLError as exc:
        raise ConfigError([f"{source}: invalid YAML: {' '.join(str(exc).split())}"]) from None
    if data is None:
        raise ConfigError([f"{source}: empty file: expected a mapping with at least 'buses'"])
    if not isinstance(data, dict):
        raise ConfigError(
            [f"{source}: the top level must be a mapping (key: value), not {_kind(data)}"]
        )
    return data
