"""The one exception type for expected faults (a damaged file, a store or workdir that does not match the command):
its message is one line naming the file (and line) and what to do, so the command layer prints it as is."""


class UserError(ValueError):
    """An expected fault the user can fix; a ValueError so that callers catching those still do."""
