"""The command-line tools around the gateway: ``imu-gateway``'s subcommands (``cli``),
and what only they use: frame decoding, the demo, the port scan and the config
reference's generator.  The gateway itself imports none of them."""
