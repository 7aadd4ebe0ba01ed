"""imu-gateway: one owner per serial bus of IMU/VG/AH/MINS attitude sensors."""

__version__ = "0.1.0"
