"""The serial side: the link (bytes only) and the bus master (the only writer)."""
