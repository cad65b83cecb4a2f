"""The exceptions stages raise: StageError for a user-facing failure, EmptyInput for an input slot with nothing in
it; imports nothing from the project, so it adds nothing to a stage's cache key (stages/engine/cache_keys.py)."""


class StageError(RuntimeError):
    """A clear, user-facing failure of one stage item (what failed, where, and what to do)."""


class EmptyInput(StageError):
    """Not a failure: the node's input slot is empty (a frame slot its video could not fill), so there is nothing to
    compute. The engine keeps that outcome in the cache like a result, with this message as the reason, and the
    nodes that need the node's output are empty too (stages/engine/scheduler.py)."""
