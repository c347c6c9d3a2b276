"""pytest configuration: make the repository root importable as `tests.*`."""
