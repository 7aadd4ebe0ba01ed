"""``python -m imu_gateway`` is ``imu-gateway``."""

import sys

from .tools.cli import main

sys.exit(main())
