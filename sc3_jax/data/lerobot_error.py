"""The error every reader of a LeRobot dataset raises (``LeRobotError``): one line naming the file or feature key at
fault; below the reader, the video decoder and the importer, which all raise it."""
from __future__ import annotations

import os

from sc3_jax.core.errors import UserError


class LeRobotError(UserError):
    """A LeRobot dataset we cannot read as asked (a UserError: one line in every command that reads one).
    ``where`` names the file or feature key at fault."""

    def __init__(self, where: str | os.PathLike, problem: str):
        self.where, self.problem = str(where), problem
        super().__init__(f"{where}: {problem}")
