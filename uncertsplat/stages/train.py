"""Stage `train` (issue 5)."""

from __future__ import annotations

from uncertsplat.errors import UserError


def run(*args, **kwargs):
    raise UserError("`train` is not implemented yet (issue 5).")
