"""User-facing errors: the CLI prints these as one paragraph, without a traceback."""

from __future__ import annotations

from pathlib import Path


class UserError(Exception):
    """An error caused by the user's input, with a message that names the file and the fix.

    Args:
        message: what is wrong, in one or two sentences.
        path: the file or folder concerned, if any.
        hint: what the user can do about it.
    """

    def __init__(self, message: str, *, path: str | Path | None = None, hint: str | None = None):
        self.message = message
        self.path = None if path is None else Path(path)
        self.hint = hint
        super().__init__(self.render())

    def render(self) -> str:
        parts = []
        if self.path is not None:
            parts.append(f"{self.path}: {self.message}")
        else:
            parts.append(self.message)
        text = parts[0]
        if self.hint:
            # messages are written without a final full stop; the hint is a sentence of its own
            text = text if text.rstrip().endswith((".", "!", "?", ":")) else text.rstrip() + "."
            text = f"{text} {self.hint}"
        return text


class StageError(UserError):
    """A pipeline stage failed; the message says which stage and why."""
