"""Errors the command-line entrypoints turn into one clear line and exit code 2."""


class ConfigError(ValueError):
    """A value that cannot work; the message names the key, the bad value and what is allowed."""


class CheckpointError(RuntimeError):
    """A checkpoint that is missing, truncated or corrupted; the message names the file."""
