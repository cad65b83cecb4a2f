"""The one exception type stages raise for a user-facing failure; imports nothing from the project, so it
adds nothing to a stage's cache key (stages/cache_keys.py)."""


class StageError(RuntimeError):
    """A clear, user-facing failure of one stage item (what failed, where, and what to do)."""
