"""docs/sparkplug.md and the generated protobuf module are what their sources make."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from support import ROOT

from imu_gateway.frontends.sparkplug import docs

PACKAGE = ROOT / "imu_gateway" / "frontends" / "sparkplug"


def test_sparkplug_document_is_up_to_date() -> None:
    assert (ROOT / "docs" / "sparkplug.md").read_text() == docs.markdown(), (
        "docs/sparkplug.md is out of date: run "
        "`python -m imu_gateway.frontends.sparkplug.docs > docs/sparkplug.md`")


def test_the_generated_payload_module_is_protoc_s_of_the_proto(tmp_path: Path) -> None:
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", f"-I{PACKAGE}",
                    f"--python_out={tmp_path}", f"--pyi_out={tmp_path}",
                    str(PACKAGE / "payload.proto")], check=True)
    for name in ("payload_pb2.py", "payload_pb2.pyi"):
        assert (tmp_path / name).read_text() == (PACKAGE / name).read_text(), (
            f"{name} is out of date: run scripts/sparkplug-proto")
