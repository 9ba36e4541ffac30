"""A validated ``replace`` shared by the settings dataclasses (``CoarseSettings``, ``ResampleSettings``)."""

from __future__ import annotations

from dataclasses import fields

from s3o_warp.errors import ConfigError


class SettingsReplace:
    """Mixin: ``replace(**overrides)`` returns a validated copy; ``_section`` names the settings in errors."""

    _section = "settings"

    def replace(self, **overrides):
        """A copy with some fields changed (validated by ``__post_init__``); unknown names raise ConfigError."""
        known = {f.name for f in fields(self)}
        for k in overrides:
            if k not in known:
                raise ConfigError(f"{self._section}.{k} is not a setting; known: {', '.join(sorted(known))}")
        vals = {f.name: getattr(self, f.name) for f in fields(self)}
        vals.update(overrides)
        return type(self)(**vals)
