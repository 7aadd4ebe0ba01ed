#!/usr/bin/env python3
"""The container's health check: GET the gateway's /api/v1/health.

Exit 0 when it answers 200 (``ok`` or ``degraded``: the process serves; a sensor or
port being down is reported in the answer, and restarting would not fix it), 1
otherwise.  ``IMU_GATEWAY_HEALTH_URL`` overrides the URL; ``HTTP_TOKEN``, when set,
is sent as the bearer token (needed with ``http.read_token_required: true``).
"""

from __future__ import annotations

import json
import os
import sys
import urllib.error
import urllib.request

DEFAULT_URL = "http://127.0.0.1:8080/api/v1/health"


def main() -> int:
    url = os.environ.get("IMU_GATEWAY_HEALTH_URL") or DEFAULT_URL
    request = urllib.request.Request(url, headers={"Accept": "application/json"})
    token = os.environ.get("HTTP_TOKEN")
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=4) as answer:
            body = json.load(answer)
    except (urllib.error.URLError, OSError, ValueError) as exc:
        print(f"unhealthy: {url}: {exc}", file=sys.stderr)
        return 1
    print(f"{body.get('status', '?')}: {body.get('sensors', {})}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
