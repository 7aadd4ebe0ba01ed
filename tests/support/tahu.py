"""Eclipse Tahu's Sparkplug B payload codec (npm ``sparkplug-payload``), run with Node:
the tests' independent reading of the gateway's payloads (tests/node/sparkplug.js)."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
from typing import Any

from . import TESTS

NODE_DIR = TESTS / "node"


class Tahu:
    """One Node process; ``decode`` and ``encode`` a payload each (one line each way)."""

    def __init__(self) -> None:
        node = shutil.which("node")
        assert node is not None, "node is needed: scripts/bootstrap --test installs it"
        assert (NODE_DIR / "node_modules" / "sparkplug-payload").is_dir(), \
            "run scripts/bootstrap --test (npm ci in tests/node)"
        self.process = subprocess.Popen(
            [node, str(NODE_DIR / "sparkplug.js")], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, text=True, env={"NODE_PATH": str(NODE_DIR / "node_modules")})

    def _ask(self, request: dict[str, Any]) -> dict[str, Any]:
        assert self.process.stdin is not None and self.process.stdout is not None
        self.process.stdin.write(json.dumps(request) + "\n")
        self.process.stdin.flush()
        answer: dict[str, Any] = json.loads(self.process.stdout.readline())
        assert "error" not in answer, answer["error"]
        return answer

    def decode(self, payload: bytes) -> dict[str, Any]:
        return self._ask({"decode": base64.b64encode(payload).decode()})

    def encode(self, payload: dict[str, Any]) -> bytes:
        return base64.b64decode(self._ask({"encode": payload})["b64"])

    def close(self) -> None:
        for pipe in (self.process.stdin, self.process.stdout):
            if pipe is not None:
                pipe.close()
        self.process.wait(10)
