"""Shipped events files for `autopower simulate --events NAME` (``NAME.events.toml``)."""
