"""Every ```yaml block of docs/*.md and README.md passes the config check
(``load_config_text``, what ``imu-gateway check-config`` runs), so a block pasted from
the docs works.

The rule, which the docs follow:

* A block is a whole config unless its first line is the comment ``# fragment``.
* A fragment (a section shown alone: ``mqtt:``, ``opcua:``, …) is checked merged into
  :data:`MINIMAL`: its top-level keys are added to that config's (``buses`` replaced
  if it has its own). :data:`MINIMAL` is the docs' running example: a native AH named
  ``boom`` with the alarm ``boom_lean`` of docs/alarms.md, which fragments refer to.
* ``${VAR}`` references are set in the environment (the docs keep secrets out of the
  file, as a reader should): each to a value of its own (two tokens are two tokens),
  and a ``…_HASH`` to a password hash (``imu-gateway hash-password``'s).
* One kind of problem is left out: a file or folder the block names that is not on
  this machine ("no such file", "no such folder": a certificate in /etc/imu-gateway, a
  journal in /var/lib/imu-gateway). Those paths are the reader's gateway's, and
  check-config says so there.
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

import pytest
import yaml

from imu_gateway.config import config_from_dict
from imu_gateway.errors import ConfigError
from imu_gateway.passwords import hash_password

ROOT = Path(__file__).resolve().parents[1]
PAGES = [*sorted((ROOT / "docs").glob("*.md")), ROOT / "README.md"]
FRAGMENT = "# fragment"
MINIMAL = {"buses": [{"name": "line-a", "port": "/dev/ttyUSB0", "protocol": "native",
                      "sensors": [{"name": "boom", "series": "AH", "alarms": [
                          {"name": "boom_lean", "field": "tilt", "above": 5.0}]}]}]}
HASH = hash_password("a password of the docs")
ABSENT_PATH = re.compile(r": no such (file|folder): ")
BLOCK = re.compile(r"^( *)```yaml\n(.*?)^\1```", re.M | re.S)


def yaml_blocks() -> list[tuple[str, str]]:
    """(page:line, the block dedented) for each ```yaml block."""
    found = []
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for match in BLOCK.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            found.append((f"{page.relative_to(ROOT)}:{line}", textwrap.dedent(match.group(2))))
    return found


BLOCKS = yaml_blocks()


def problems(block: str) -> list[str]:
    try:
        data = yaml.safe_load(block)
    except yaml.YAMLError as exc:
        return [f"invalid YAML: {' '.join(str(exc).split())}"]
    if not isinstance(data, dict):
        return [f"not a mapping: {type(data).__name__}"]
    if block.startswith(FRAGMENT):
        data = {**MINIMAL, **data}
    names = re.findall(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}", block)
    try:
        config_from_dict(data, env={name: HASH if name.endswith("_HASH") else f"secret-{name}"
                                    for name in names})
    except ConfigError as exc:
        return [p for p in exc.problems if not ABSENT_PATH.search(p)]
    return []


def test_the_docs_have_yaml_blocks_and_fragments() -> None:
    assert len(BLOCKS) >= 10
    assert any(block.startswith(FRAGMENT) for _, block in BLOCKS)


@pytest.mark.parametrize(("where", "block"), BLOCKS, ids=[where for where, _ in BLOCKS])
def test_every_yaml_block_passes_check_config(where: str, block: str) -> None:
    assert problems(block) == [], f"{where}: {block}"


def test_a_broken_block_is_caught() -> None:
    """What docs/opcua.md once showed (braces doubled by its generator's f-string)."""
    assert problems(f'{FRAGMENT}\nopcua:\n  users: {{{{operator: "${{{{OPCUA_PASSWORD}}}}"}}}}\n')
    assert problems("mqtt:\n  url: mqtt://broker:1883\n") == ["buses: required"]
