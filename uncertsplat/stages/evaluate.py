"""Stage `evaluate` (issue 6)."""

from __future__ import annotations

from uncertsplat.errors import UserError


def run(*args, **kwargs):
    raise UserError("`evaluate` is not implemented yet (issue 6).")
