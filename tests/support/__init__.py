"""What the tests share beside their fixtures (``tests/conftest.py``): the gateway run
inside a test (``harness``), the real peers each test starts (``broker``: mosquitto;
``nats_cluster``; ``tahu``: Eclipse Tahu's reading of Sparkplug payloads), the
protocol documents' frames (``vectors``) and the virtual-time line (``virtual_line``).

The folders beside this one mirror the package: the tests of ``imu_gateway/bus/`` are
in ``tests/bus/``, those of ``imu_gateway/frontends/mqtt/`` in
``tests/frontends/mqtt/``; the tests of the whole product (layering, sizes, docs,
install, soak) are in ``tests/`` itself.
"""

from pathlib import Path

#: the repository's root, and the tests' folder (its data: ``configs/``, ``node/``)
ROOT = Path(__file__).resolve().parents[2]
TESTS = ROOT / "tests"
