"""Every catalogue command against every layer that carries it.

The catalogue (``imu_gateway.commands.CATALOGUE``) is one row per command; each protocol
has one row per command it can carry (``protocol.exchanges``); the Modbus TCP command
block, REST's routes and ``docs/commands.md`` are derived from the catalogue.  These
tests hold the rows to each other: a command added to one layer and forgotten in
another fails here, by name.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import pytest
from support import ROOT

from imu_gateway.commands import CATALOGUE, BusEffect, commands_for, validate
from imu_gateway.frontends.modbus import map as mm
from imu_gateway.model import KnownSettings, Series, WireProtocol
from imu_gateway.protocol.exchanges import (
    MODBUS_COMMANDS,
    NATIVE_COMMANDS,
    Answer,
    Effect,
    Exchange,
    adapter_for,
)
from imu_gateway.simulator.sensor import SimSensor, make_sensor
from imu_gateway.tools import command_reference

DOC = ROOT / "docs" / "commands.md"
WIRES = tuple(WireProtocol)


CASES = [(spec.name, series, wire, args)
         for spec in CATALOGUE.values() for series in Series if series in spec.series
         for wire in WIRES if adapter_for(wire).carries(spec.name)
         for args in command_reference.choices(spec)]


def test_commands_md_is_up_to_date() -> None:
    text = DOC.read_text(encoding="utf-8")
    assert command_reference.render(text) == text, (
        "docs/commands.md is out of date: run scripts/command-reference")
    for section in command_reference.SECTIONS:
        assert f"<!-- generated: {section} -->" in text


def test_the_protocol_rows_are_catalogue_commands() -> None:
    """No row for a command the catalogue lacks; the native document has all of them,
    and the Modbus document lacks just the declination and the magnetometer calibration
    (native 2.21-2.26)."""
    assert set(NATIVE_COMMANDS) == set(CATALOGUE)
    assert set(CATALOGUE) - set(MODBUS_COMMANDS) == {"set_declination", "mag_calibration"}
    for name in CATALOGUE:
        for wire in WIRES:
            assert adapter_for(wire).carries(name) == (
                name in (NATIVE_COMMANDS if wire is WireProtocol.NATIVE else MODBUS_COMMANDS))


def test_commands_for_is_the_catalogue_series_and_the_protocol_rows() -> None:
    for series in Series:
        for wire in WIRES:
            expected = {n for n, spec in CATALOGUE.items()
                        if series in spec.series and adapter_for(wire).carries(n)}
            assert commands_for(series, wire) == expected


def _effect_of(effects: list[Effect]) -> BusEffect:
    if any(e.new_baud for e in effects):
        return BusEffect.NEW_BAUD
    if any(e.new_address is not None for e in effects):
        return BusEffect.NEW_ADDRESS
    if any(e.busy_for or e.busy_until_done for e in effects):
        return BusEffect.BUSY
    return BusEffect.NONE


def _carry_out(sensor: SimSensor, exchanges: list[Exchange]) -> list[Answer]:
    """Each request heard by the simulated sensor, and its answer matched by the
    exchange's own rule (an exchange that expects no answer gets none)."""
    framer = adapter_for(sensor.protocol).new_framer()
    answers = []
    for now, exchange in enumerate(exchanges, start=1):
        heard = sensor.hear(exchange.request, float(now))
        frames = [f for out in heard for f in framer.feed(out.frame)]
        if exchange.answer_bytes == 0:
            assert frames == [], exchange.label
            continue
        matched = [a for f in frames if (a := exchange.match(f)) is not None]
        assert len(matched) == 1, (exchange.label, frames)
        answers.append(matched[0])
    return answers


@pytest.mark.parametrize(("name", "series", "wire", "args"), CASES,
                         ids=[f"{n}-{s.name}-{w.name}-{a}" for n, s, w, a in CASES])
def test_each_command_on_each_protocol_reaches_the_sensor_and_is_answered(
        name: str, series: Series, wire: WireProtocol, args: dict[str, Any]) -> None:
    """Catalogue -> protocol row -> the simulated sensor -> the row's answer rule -> what
    the catalogue learns: one pass per command, series, protocol and choice.  The row's
    effects are the ones the catalogue says the command has."""
    spec = CATALOGUE[name]
    command = validate(name, args, series, wire)
    sensor = make_sensor(wire, series)
    exchanges = adapter_for(wire).command(series, sensor.address, name, command.args)
    # the catalogue says what a command may do; a protocol may not need it (a native
    # gyro calibration is over when answered), never something else
    assert _effect_of([e.effect for e in exchanges]) in (spec.bus, BusEffect.NONE)
    answers = _carry_out(sensor, exchanges)
    assert answers and all(a.ok for a in answers), answers
    values: dict[str, Any] = {}
    for answer in answers:
        values.update(answer.values)
    learned = spec.learns(command.args, values)
    assert isinstance(learned, KnownSettings)
    if learned.zero_type is not None:  # what the gateway now believes, the sensor holds
        assert learned.zero_type == sensor.settings.zero_type
    if learned.declination is not None:
        assert learned.declination == sensor.settings.declination


@pytest.mark.parametrize("name", list(CATALOGUE))
def test_some_protocol_has_the_bus_effect_the_catalogue_names(name: str) -> None:
    spec = CATALOGUE[name]
    seen = {_effect_of([e.effect for e in adapter_for(wire).command(
                series, 1, name, validate(name, args, series, wire).args)])
            for _, series, wire, args in (c for c in CASES if c[0] == name)}
    assert spec.bus in seen


@pytest.mark.parametrize("name", list(CATALOGUE))
def test_each_example_is_valid_where_the_command_exists(name: str) -> None:
    spec = CATALOGUE[name]
    for series in spec.series:
        for wire in WIRES:
            if name in commands_for(series, wire):
                assert validate(name, spec.example, series, wire).args == dict(spec.example)


@pytest.mark.parametrize("name", [n for n, s in CATALOGUE.items() if s.register is not None])
def test_each_register_command_round_trips_through_its_modbus_tcp_register(name: str) -> None:
    """A write of the command's register gives the catalogue's arguments back, and a
    read shows what that command taught (the choice's code, the float)."""
    spec = CATALOGUE[name]
    assert spec.register is not None
    reg = mm.BY_ADDRESS[spec.register.address]
    assert reg.command == name and reg.series == spec.series
    setting = spec.register.setting
    assert setting is None or setting in {f.name for f in dataclasses.fields(KnownSettings)}
    for args in command_reference.choices(spec):
        series = next(iter(spec.series))
        command = validate(name, args, series, WireProtocol.NATIVE)
        image = mm.SensorImage(series, WireProtocol.NATIVE, 0, 1000)
        image.refresh_commands(_busy_snapshot(), spec.learns(command.args, command.args))
        words = [int.from_bytes(image.words[2 * a: 2 * a + 2], "big")
                 for a in range(reg.address, reg.address + reg.type.words)]
        if not spec.args.model_fields:
            words = [1]  # a trigger reads what is under way, and is written 1
        assert mm.command_args(spec, words) == command.args


def _busy_snapshot() -> Any:
    from imu_gateway.cache import Snapshot, Status

    return Snapshot("s", None, 0, None, None, Status.OFFLINE, online=True, busy=True,
                    streaming=False, errors=0)


def test_rest_has_one_route_per_command() -> None:
    """(The committed OpenAPI document is what the app serves:
    tests/frontends/rest/test_rest.py.)"""
    document = json.loads((DOC.parent.parent / "openapi" / "openapi.json").read_text())
    commands = {path.rsplit("/", 1)[1] for path in document["paths"]
                if path.startswith("/api/v1/sensors/{name}/commands/")}
    assert commands == set(CATALOGUE)
    bodies = document["components"]["schemas"]
    assert {spec.args.__name__ for spec in CATALOGUE.values()} <= set(bodies)
