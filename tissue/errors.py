"""The one exception users see: its message names the file, field or element ids at fault."""


class TissueError(ValueError):
    """Bad input or an unrecoverable numerical state, explained in one line."""
