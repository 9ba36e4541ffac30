"""Errors a user can act on: one line that names the file or setting and the fix."""


class InputError(ValueError):
    """Bad user input (a file, a folder, a setting). The message is one line: what, where, the fix."""


class ConfigError(InputError):
    """A bad configuration key or value; the message names the key."""
