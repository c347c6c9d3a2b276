"""The config of a run as a whole: the one error a bad config raises, whatever the stage
(view synthesis or regression), so that every command line maps it to exit status 2."""

from __future__ import annotations


class ConfigError(ValueError):
  """A config whose parts do not fit together or name something unknown (raised before any data
  or model is built)."""
