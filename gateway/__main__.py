"""``python -m gateway`` is ``imu-gateway``."""

import sys

from .cli import main

sys.exit(main())
