"""The generated parts of ``docs/commands.md``, from the command catalogue and the
protocol rows (``scripts/command-reference`` writes them; a test fails while the file
is stale).

The prose of that file is written by hand.  Between each pair of markers

    <!-- generated: NAME -->
    <!-- end generated -->

this module writes the section ``NAME`` anew: the catalogue table (``catalogue``) and
the Modbus TCP command registers (``registers``).  The wire columns are read off the
requests the protocol rows really build, so they cannot drift from what is sent.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from ..commands import CATALOGUE, CommandSpec, validate
from ..modbus_codes import READ_HOLDING, READ_INPUT, WRITE_SINGLE
from ..model import Series, WireProtocol
from ..protocol.exchanges import adapter_for

DOC = Path("docs/commands.md")
_SECTION = re.compile(r"(<!-- generated: (\w+) -->\n).*?(<!-- end generated -->)", re.S)


def choices(spec: CommandSpec) -> Iterator[dict[str, Any]]:
    """Arguments that together reach every request the command can make: each value
    of a choice, else the row's example (or none)."""
    for name, prop in spec.args.model_json_schema().get("properties", {}).items():
        if "enum" in prop:
            yield from ({name: value} for value in prop["enum"])
            return
    yield dict(spec.example)


def _native_code(request: bytes) -> str:
    return f"0x{request[3]:02X}"  # 77, length, address, command, …


def _modbus_step(request: bytes) -> str:
    function = request[1]
    start, count = int.from_bytes(request[2:4], "big"), int.from_bytes(request[4:6], "big")
    if function in (READ_HOLDING, READ_INPUT):
        return f"reads 0x{start:02X}" + (f"–0x{start + count - 1:02X}" if count > 1 else "")
    assert function == WRITE_SINGLE, function
    return f"0x{start:02X}"


def _wire(spec: CommandSpec, protocol: WireProtocol, show: Callable[[bytes], str]) -> str:
    """The requests the protocol's row sends: ``then`` between the steps of one
    command, ``/`` between its choices, and a series that differs named apart
    (``0x0D; AH: 0x0D then 0x07``)."""
    adapter = adapter_for(protocol)
    if not adapter.carries(spec.name):
        return "none"
    texts: dict[Series, str] = {}
    for series in (s for s in Series if s in spec.series):
        sequences = []
        for args in choices(spec):
            command = validate(spec.name, args, series, protocol)
            exchanges = adapter.command(series, 1, spec.name, command.args)
            sequences.append(" then ".join(show(e.request) for e in exchanges))
        texts[series] = " / ".join(dict.fromkeys(sequences))
    usual = max(texts.values(), key=list(texts.values()).count)
    return usual + "".join(f"; {series.name}: {text}" for series, text in texts.items()
                           if text != usual)


def _arguments(spec: CommandSpec) -> str:
    properties: Mapping[str, Any] = spec.args.model_json_schema().get("properties", {})
    if not properties:
        return "none"
    parts = []
    for name, prop in properties.items():
        if "enum" in prop:
            choices = " \\| ".join(f'"{value}"' for value in prop["enum"])
            parts.append(f'`{{"{name}": {choices}}}`')
        elif "minimum" in prop and prop.get("type") == "number":
            low, high = _number(prop["minimum"]), _number(prop["maximum"])
            parts.append(f'`{{"{name}": x}}`, {low} ≤ x ≤ {high}')
        else:
            parts.append(f'`{{"{name}": n}}`: {prop.get("description", prop.get("type"))}')
    return "; ".join(parts)


def _number(value: float) -> str:
    return f"{value:g}".replace("-", "−")


def catalogue() -> list[str]:
    lines = ["| command | arguments | " + " | ".join(s.name for s in Series)
             + " | native | Modbus RTU | retried | summary |",
             "|---|---|" + "---|" * len(Series) + "---|---|---|---|"]
    for spec in CATALOGUE.values():
        has = " | ".join("✓" if s in spec.series else "" for s in Series)
        lines.append(f"| `{spec.name}` | {_arguments(spec)} | {has} | "
                     f"{_wire(spec, WireProtocol.NATIVE, _native_code)} | "
                     f"{_wire(spec, WireProtocol.MODBUS, _modbus_step)} | "
                     f"{'✓' if spec.idempotent else ''} | {spec.summary} |")
    return lines


def _series(spec: CommandSpec) -> str:
    return "" if spec.series == frozenset(Series) else \
        f" ({', '.join(s.name for s in Series if s in spec.series)})"


def registers() -> list[str]:
    lines = ["| register | type | command | write | reads |", "|---|---|---|---|---|"]
    for spec in CATALOGUE.values():
        reg = spec.register
        if reg is None:
            continue
        if spec.argument is None:
            kind, write = "u16", "1"
        elif reg.codes:
            kind, write = "u16", ", ".join(f"{code} {choice}" for choice, code in reg.codes.items())
        else:
            kind, write = "f32", f"{spec.argument}, FC16 of both registers"
        span = f"{reg.address}" if kind == "u16" else f"{reg.address}–{reg.address + 1}"
        reads = reg.description.split("; ", 1)[-1] if "; " in reg.description else ""
        lines.append(f"| {span} | {kind} | `{spec.name}`{_series(spec)} | {write} | {reads} |")
    without = [f"`{spec.name}`" for spec in CATALOGUE.values() if spec.register is None]
    lines += ["", f"{', '.join(without[:-1])} and {without[-1]} have no register."]
    return lines


SECTIONS: Mapping[str, Callable[[], list[str]]] = {"catalogue": catalogue,
                                                    "registers": registers}


def render(text: str) -> str:
    """``text`` with every generated section written anew."""
    def section(match: re.Match[str]) -> str:
        body = "\n".join(SECTIONS[match.group(2)]())
        return f"{match.group(1)}{body}\n{match.group(3)}"

    return _SECTION.sub(section, text)


def main() -> None:
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else DOC
    path.write_text(render(path.read_text(encoding="utf-8")), encoding="utf-8")
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
