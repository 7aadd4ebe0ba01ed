"""The protocol layer stays sans-IO (the layering rule, docs/architecture.md).

Every module of ``imu_gateway/protocol`` may import only the standard library, pymodbus,
``imu_gateway.protocol``, ``imu_gateway.model``, ``imu_gateway.errors`` (the exception tree) and
``imu_gateway.modbus_codes`` (Modbus's numbers), and none of the standard library's I/O,
clock or concurrency modules.  Checked on the
source with ``ast``, so nothing is run.
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest

PROTOCOL = Path(__file__).resolve().parents[1] / "imu_gateway" / "protocol"
PACKAGE = "imu_gateway.protocol"
ALLOWED_PROJECT = ("imu_gateway.protocol", "imu_gateway.model", "imu_gateway.errors",
                   "imu_gateway.modbus_codes")
ALLOWED_THIRD_PARTY = ("pymodbus",)
FORBIDDEN = frozenset(
    {"asyncio", "serial", "time", "socket", "threading", "selectors", "subprocess",
     "multiprocessing", "concurrent"}
)
MODULES = sorted(PROTOCOL.glob("*.py"))


def package_imports(path: Path, package: str) -> list[str]:
    """Absolute dotted names of everything ``path``, a module of ``package``, imports
    (relative ones resolved)."""
    parts = package.split(".")
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = parts[: len(parts) - (node.level - 1)] if node.level else []
            if node.module:
                names.append(".".join([*base, node.module]))
            else:
                names += [".".join([*base, alias.name]) for alias in node.names]
    return names


def imported_names(path: Path) -> list[str]:
    """What a module of ``imu_gateway.protocol`` imports."""
    return package_imports(path, PACKAGE)


def _within(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def test_protocol_modules_found() -> None:
    assert {p.name for p in MODULES} >= {"errors.py", "bcd.py", "native.py", "modbus_rtu.py"}


def test_resolver() -> None:
    assert imported_names(PROTOCOL / "native.py").count("imu_gateway.model") == 1


@pytest.mark.parametrize("path", MODULES, ids=lambda p: p.name)
def test_protocol_imports_only_allowed(path: Path) -> None:
    for name in imported_names(path):
        top = name.split(".")[0]
        assert top not in FORBIDDEN, f"{path.name} imports {name}: protocol code does no I/O"
        allowed = (
            top in sys.stdlib_module_names
            or any(_within(name, p) for p in ALLOWED_THIRD_PARTY + ALLOWED_PROJECT)
        )
        assert allowed, f"{path.name} imports {name}"


GATEWAY = PROTOCOL.parent
FRONTENDS = GATEWAY / "frontends"
MQTT_LINK = GATEWAY / "mqtt_link"
#: every subpackage of ``frontends/`` is a front end; beside them, only their shared parts
FRONT_END_PACKAGES = sorted(p.parent.name for p in FRONTENDS.glob("*/__init__.py"))
SHARED = "imu_gateway.frontends.common"
#: what the MQTT transport may import of the gateway (and paho, and the standard library)
MQTT_LINK_ALLOWED = ("imu_gateway.mqtt_link", "imu_gateway.config", "imu_gateway.errors",
                     "imu_gateway.supervise")


def module_imports(path: Path) -> list[str]:
    """``package_imports`` for any module of the gateway: its package is its folder."""
    return package_imports(path, ".".join(path.parent.relative_to(GATEWAY.parent).parts))


def frontend_of(path: Path) -> str | None:
    """The front end a module of ``frontends/`` belongs to (``None``: a shared part)."""
    parts = path.relative_to(FRONTENDS).parts
    return parts[0] if len(parts) > 1 else None


def test_front_ends_found() -> None:
    assert {"modbus", "mqtt", "opcua", "rest", "sparkplug"} <= set(FRONT_END_PACKAGES)


def test_front_ends_are_packages() -> None:
    """The front ends' folder holds front ends (each a package) and their one shared
    module, nothing flat beside them."""
    flat = sorted(p.name for p in FRONTENDS.glob("*.py"))
    assert flat == ["__init__.py", "common.py"], flat


@pytest.mark.parametrize("path", sorted(FRONTENDS.rglob("*.py")),
                         ids=lambda p: str(p.relative_to(FRONTENDS)))
def test_front_ends_use_neither_protocol_nor_bus_nor_each_other(path: Path) -> None:
    """The layering rule (docs/architecture.md): a front end reads the cache and asks the
    gateway; it never touches the wire's code, and a change to one front end cannot
    break another.  Of its siblings it uses only ``frontends/common.py``, and of the
    transports ``mqtt_link``."""
    own = frontend_of(path)
    for name in module_imports(path):
        assert not _within(name, "imu_gateway.protocol"), f"{path.name} imports {name}"
        assert not _within(name, "imu_gateway.bus"), f"{path.name} imports {name}"
        if _within(name, "imu_gateway.frontends") and name != "imu_gateway.frontends":
            allowed = _within(name, SHARED) or (
                own is not None and _within(name, f"imu_gateway.frontends.{own}"))
            assert allowed, f"{path.relative_to(FRONTENDS)} imports {name}"


def test_frontend_resolver() -> None:
    names = module_imports(FRONTENDS / "mqtt" / "states.py")
    assert "imu_gateway.cache" in names and "imu_gateway.frontends.common" in names
    assert "imu_gateway.frontends.mqtt.side" in names
    names = module_imports(FRONTENDS / "rest" / "server.py")
    assert "imu_gateway.config" in names and "imu_gateway.frontends.common" in names
    assert "imu_gateway.frontends.rest.routes" in names
    assert frontend_of(FRONTENDS / "common.py") is None
    assert frontend_of(FRONTENDS / "sparkplug" / "node.py") == "sparkplug"


@pytest.mark.parametrize("path", sorted(MQTT_LINK.glob("*.py")), ids=lambda p: p.name)
def test_the_mqtt_link_is_a_transport(path: Path) -> None:
    """Both MQTT front ends share the transport; it knows brokers, paho and the config,
    never a front end, the cache, the commands or a bus."""
    for name in module_imports(path):
        if not _within(name, "imu_gateway"):
            top = name.split(".")[0]
            assert top in sys.stdlib_module_names or top == "paho", \
                f"{path.name} imports {name}"
        else:
            assert any(_within(name, p) for p in MQTT_LINK_ALLOWED), \
                f"{path.name} imports {name}"


def test_the_cache_is_a_passive_store() -> None:
    """The cache knows readings and states, not commands nor buses: nothing calls
    from it into a bus (on-demand reads go through the gateway object)."""
    for name in package_imports(PROTOCOL.parent / "cache.py", "imu_gateway"):
        assert not _within(name, "imu_gateway.commands"), name
        assert not _within(name, "imu_gateway.bus"), name
        assert not _within(name, "imu_gateway.frontends"), name


@pytest.mark.parametrize("path", sorted(FRONTENDS.rglob("*.py")), ids=lambda p: p.name)
def test_front_ends_never_reach_into_a_bus_master(path: Path) -> None:
    """A bus master's state changes on its own thread: a front end reads the frozen
    snapshots it publishes through the cache (``imu_gateway.stats()``,
    ``gateway.sensor_stats()``), never the master itself."""
    text = path.read_text(encoding="utf-8")
    assert not re.search(r"\.(master|masters|runners|_runner_of)\b", text), path.name


@pytest.mark.parametrize("path", sorted((PROTOCOL.parent / "bus").glob("*.py")),
                         ids=lambda p: p.name)
def test_a_bus_imports_no_front_end(path: Path) -> None:
    for name in package_imports(path, "imu_gateway.bus"):
        assert not _within(name, "imu_gateway.frontends"), f"{path.name} imports {name}"
        assert not _within(name, "imu_gateway.app"), f"{path.name} imports {name}"


def test_package_resolver() -> None:
    assert "imu_gateway.errors" in package_imports(PROTOCOL.parent / "cache.py", "imu_gateway")
    assert "imu_gateway.errors" in package_imports(PROTOCOL.parent / "bus" / "master.py",
                                               "imu_gateway.bus")


def test_the_gateway_imports_none_of_the_tools() -> None:
    """The command-line tools sit on top: nothing below them imports them."""
    for path in GATEWAY.rglob("*.py"):
        if "tools" in path.relative_to(GATEWAY).parts or path.name == "__main__.py":
            continue
        package = ".".join(path.parent.relative_to(GATEWAY.parent).parts)
        for name in package_imports(path, package):
            assert not _within(name, "imu_gateway.tools"), f"{path} imports {name}"


CONFIG = GATEWAY / "config"


def _modules() -> dict[str, Path]:
    """Every module of the gateway by dotted name (a package by its ``__init__``)."""
    out = {}
    for path in GATEWAY.rglob("*.py"):
        parts = path.relative_to(GATEWAY.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _ancestors(name: str) -> set[str]:
    parts = name.split(".")
    return {".".join(parts[:k]) for k in range(1, len(parts))}


def package_graph() -> dict[str, set[str]]:
    """Which modules of the gateway each one imports, counting imports inside functions
    and under ``if TYPE_CHECKING:`` (a late import is a loop all the same).  Importing
    ``a.b.c`` runs the ``__init__`` of ``a`` and ``a.b`` too, unless the importer is
    inside them (its packages are already being imported)."""
    modules = _modules()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        own = _ancestors(name) | ({name} if path.name == "__init__.py" else set())
        edges: set[str] = set()
        for target in module_imports(path):
            while target not in modules and "." in target:  # ``from m import attr``
                target = target.rsplit(".", 1)[0]
            edges |= {m for m in _ancestors(target) | {target} if m in modules} - own
        graph[name] = edges - {name}
    return graph


def import_loop(graph: dict[str, set[str]]) -> list[str] | None:
    """One loop of ``graph`` (``[a, b, a]``), or ``None``: a depth-first walk."""
    done: set[str] = set()

    def walk(node: str, trail: list[str]) -> list[str] | None:
        if node in trail:
            return [*trail[trail.index(node):], node]
        if node in done:
            return None
        for nxt in sorted(graph.get(node, ())):
            found = walk(nxt, [*trail, node])
            if found:
                return found
        done.add(node)
        return None

    for start in sorted(graph):
        found = walk(start, [])
        if found:
            return found
    return None


def test_import_loop_finder() -> None:
    assert import_loop({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert import_loop({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None
    graph = package_graph()
    assert graph["imu_gateway.config"] >= {"imu_gateway.config.loading",
                                           "imu_gateway.config.schema"}
    # an import of a module runs its packages' ``__init__`` first; not its own packages'
    assert "imu_gateway.frontends" in graph["imu_gateway.app"]
    assert "imu_gateway.config" not in graph["imu_gateway.config.schema"]


def test_no_import_loop_in_the_package() -> None:
    """No module of the gateway half-exists while another reads it: the error tree
    imports no config, the config's checks across keys live where the schema does not
    import them back (every way of building a config runs them), and a late import
    inside a function counts as much as one at the top."""
    loop = import_loop(package_graph())
    assert loop is None, f"import loop: {' -> '.join(loop or [])}"


def test_config_modules_share_no_private_name() -> None:
    """A name another module uses is public; one kept private (``_x``) is its module's own."""
    crossing = [
        f"{path.name}: from {'.' * node.level}{node.module or ''} import {alias.name}"
        for path in sorted(CONFIG.glob("*.py"))
        for node in ast.walk(ast.parse(path.read_text(), str(path)))
        if isinstance(node, ast.ImportFrom) and node.level
        for alias in node.names if alias.name.startswith("_")
    ]
    assert not crossing, "private names imported across imu_gateway/config:\n" + \
        "\n".join(crossing)


# ------------------------------------------------------------------ the bus core is sans-IO

BUS = GATEWAY / "bus"
#: The bus's decisions: no clock, no port, no thread, no loop (time is an argument, as
#: in the protocol package).  ``line`` is one of them: the wire as the schedule sees it
#: (the schedule and its outcomes import it).  The edge that does the I/O is
#: ``master``, ``port``, ``link``, ``reactor`` and ``runner``.
BUS_CORE = ("schedule", "membership", "jobs", "phase", "timing", "sensor_state", "outcomes",
            "diagnosis", "events", "trace", "line")
BUS_FORBIDDEN = FORBIDDEN | {"select"}
#: What the core may import of the project besides itself: the protocol, the model,
#: the exception tree, Modbus's numbers and the command catalogue; and two stores of
#: plain data: ``config`` (the frozen settings a schedule runs by) and ``stats`` (the
#: running totals it keeps).  Neither does I/O on import or in what the core uses.
BUS_CORE_ALLOWED = ("imu_gateway.protocol", "imu_gateway.model", "imu_gateway.errors",
                    "imu_gateway.modbus_codes", "imu_gateway.commands", "imu_gateway.config",
                    "imu_gateway.stats", *(f"imu_gateway.bus.{m}" for m in BUS_CORE))


@pytest.mark.parametrize("module", BUS_CORE)
def test_the_bus_core_does_no_io(module: str) -> None:
    path = BUS / f"{module}.py"
    for name in package_imports(path, "imu_gateway.bus"):
        top = name.split(".")[0]
        assert top not in BUS_FORBIDDEN, \
            f"bus/{path.name} imports {name}: the bus core does no I/O; time is an argument"
        if top == "imu_gateway":
            assert any(_within(name, p) for p in BUS_CORE_ALLOWED), \
                f"bus/{path.name} imports {name}"
        else:
            assert top in sys.stdlib_module_names, f"bus/{path.name} imports {name}"


def test_bus_core_resolver() -> None:
    names = package_imports(BUS / "schedule.py", "imu_gateway.bus")
    assert "imu_gateway.bus.line" in names and "imu_gateway.protocol.exchanges" in names


def _assigned(tree: ast.AST) -> list[ast.expr]:
    """Everything a module assigns to, augments or deletes (the targets)."""
    found: list[ast.expr] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign | ast.Delete):
            found += node.targets
        elif isinstance(node, ast.AugAssign | ast.AnnAssign):
            found.append(node.target)
    return found


def _through_schedule(target: ast.expr) -> bool:
    """Whether ``target`` is state reached through a schedule (``x.schedule.port_open``,
    ``schedule.outcomes.tracing``, ``schedule.sensors["a"].address``); ``x.schedule``
    itself is its holder's own attribute."""
    for node in ast.walk(target):
        if isinstance(node, ast.Attribute | ast.Subscript):
            inner = node.value
            if (isinstance(inner, ast.Name) and inner.id == "schedule") or \
                    (isinstance(inner, ast.Attribute) and inner.attr == "schedule"):
                return True
    return False


def test_only_the_schedule_changes_its_state() -> None:
    """The schedule's state changes through its own methods, named for what they mean
    (``start``, ``close``, ``count_reading``, …), so that every change of it is found in
    ``bus/schedule.py``.  (Aliases, ``s = schedule.sensors["a"]; s.x = 1``, are not
    followed: the rule is checked where it is written plainly.)"""
    assert [_through_schedule(t) for t in _assigned(ast.parse(
        "self.schedule.port_open = 1; schedule.sensors['a'].x += 1; self.schedule = 1"))] \
        == [True, True, False]
    found = []
    for path in sorted(GATEWAY.rglob("*.py")):
        if path == BUS / "schedule.py":
            continue
        found += [f"{path.relative_to(GATEWAY)}:{t.lineno} {ast.unparse(t)}"
                  for t in _assigned(ast.parse(path.read_text(), str(path)))
                  if _through_schedule(t)]
    assert found == []


def test_frames_are_told_apart_by_their_type() -> None:
    """The frames the protocol hands the bus are a union (``exchanges.Frame``): the bus
    matches on it, never duck-types a frame with ``getattr``."""
    for path in (BUS / "outcomes.py", BUS / "diagnosis.py", PROTOCOL / "exchanges.py"):
        calls = [n for n in ast.walk(ast.parse(path.read_text(), str(path)))
                 if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
                 and n.func.id == "getattr"]
        assert calls == [], f"{path.name}:{calls[0].lineno} duck-types with getattr"


def _parts(hint: object) -> list[object]:
    """A type hint and every type inside it (``Callable[[Any], None]``: ``Any`` too)."""
    from typing import get_args

    inner = hint if isinstance(hint, list) else get_args(hint)  # (a Callable's arguments)
    return [hint, *(p for arg in inner for p in _parts(arg))]


def test_frames_and_outcomes_cross_typed() -> None:
    """No ``Any`` where a frame crosses from the protocol to the bus, nor in what a bus
    master tells whoever asked (``Done``)."""
    from typing import Any, get_type_hints

    from imu_gateway.bus import line, master, outcomes
    from imu_gateway.protocol import exchanges

    hints = {
        "Exchange.match": get_type_hints(exchanges.Exchange)["match"],
        "Framer.feed": get_type_hints(exchanges.Framer.feed)["return"],
        "Framer.expire": get_type_hints(exchanges.Framer.expire)["return"],
        "ProtocolAdapter.unsolicited": get_type_hints(
            exchanges.ProtocolAdapter.unsolicited)["frame"],
        "Line.on_frame": get_type_hints(line.Line.__init__)["on_frame"],
        "Outcomes.frame": get_type_hints(outcomes.Outcomes.frame)["frame"],
        "master.Done": master.Done,
    }
    assert [where for where, hint in hints.items() if Any in _parts(hint)] == []


@pytest.mark.parametrize("module", ["alarms.py"])
def test_the_alarms_are_sans_io(module: str) -> None:
    """The alarms' state model (docs/alarms.md) takes time as an argument, as the
    protocol does: no clock, thread, loop or file, so every transition is tested in
    virtual time (tests/test_alarms.py).  Of the gateway it knows only the errors."""
    for name in package_imports(GATEWAY / module, "imu_gateway"):
        top = name.split(".")[0]
        assert top not in FORBIDDEN, f"{module} imports {name}"
        assert top in sys.stdlib_module_names or _within(name, "imu_gateway.errors"), \
            f"{module} imports {name}"
