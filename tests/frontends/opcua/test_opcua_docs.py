"""docs/opcua.md is what its rows make."""

from __future__ import annotations

from support import ROOT

from imu_gateway.frontends.opcua import docs

DOC = ROOT / "docs" / "opcua.md"


def test_opcua_document_is_up_to_date() -> None:
    assert DOC.read_text() == docs.markdown(), (
        "docs/opcua.md is out of date: run "
        "`python -m imu_gateway.frontends.opcua.docs > docs/opcua.md`")
