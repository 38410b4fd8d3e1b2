"""Error types shared by the library edges (loaders, CLI).

`InputError` formats as ``file:line: field: what is wrong and how to fix it`` so that
every bad-input message a user sees has the same shape and names what to change.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input (a file, a column, an option), with where it is and how to fix it."""

    def __init__(
        self,
        message: str,
        *,
        file: str | None = None,
        line: int | None = None,
        field: str | None = None,
    ):
        self.file = file
        self.line = None if line is None else int(line)  # a numpy index too
        self.field = field
        self.message = message
        where = ""
        if file is not None:
            where = f"{file}:{line}: " if line is not None else f"{file}: "
        what = f"{field}: " if field else ""
        super().__init__(f"{where}{what}{message}")
