"""Sparkplug B (docs/sparkplug.md): the gateway as an edge node, each sensor a device."""
