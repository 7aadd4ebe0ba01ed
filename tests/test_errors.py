"""One exception tree, one vocabulary (``imu_gateway.errors``).

Every error class the gateway defines descends from ``GatewayError``, and every kind
of failed request has one row: the name REST and MQTT show, the HTTP status and the
Modbus exception code."""

from __future__ import annotations

import ast
import importlib
import pkgutil
from pathlib import Path

import imu_gateway
from imu_gateway.errors import KINDS, ErrorKind, GatewayError, RequestFailed


def test_every_exception_class_of_the_gateway_is_in_the_one_tree() -> None:
    root = Path(imu_gateway.__file__).parent
    outside = []
    for info in pkgutil.walk_packages([str(root)], "imu_gateway."):
        if info.name.endswith("__main__"):
            continue  # importing it runs the command line
        module = importlib.import_module(info.name)
        for node in ast.walk(ast.parse(Path(module.__file__ or "").read_text())):
            if isinstance(node, ast.ClassDef):
                cls = getattr(module, node.name, None)
                if isinstance(cls, type) and issubclass(cls, BaseException) and \
                        not issubclass(cls, GatewayError):
                    outside.append(f"{info.name}.{node.name}")
    assert outside == []


def test_every_kind_has_one_row_and_a_status_that_is_an_error() -> None:
    assert set(KINDS) == set(ErrorKind)
    assert all(400 <= row.status < 600 for row in KINDS.values())
    assert len({kind.value for kind in ErrorKind}) == len(ErrorKind)


def test_a_failed_request_carries_its_kind_and_status() -> None:
    failed = RequestFailed(ErrorKind.BUSY, "boom is saving")
    assert failed.kind is ErrorKind.BUSY and failed.status == 409
    assert str(failed) == "boom is saving"
    assert isinstance(failed, GatewayError)
