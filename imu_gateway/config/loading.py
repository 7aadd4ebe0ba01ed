"""Reading a config: YAML with duplicate keys refused, ``${VAR}`` from the
environment, and every problem found at once."""

from __future__ import annotations

import contextlib
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
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node)
        try:
            first = seen.setdefault(key, key_node.start_mark.line)
        except TypeError:  # an unhashable key: SafeLoader reports it
            continue
        if first != key_node.start_mark.line:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {show(key)} (first given on line {first + 1})",
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
    return config_from_dict(data, env)


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
