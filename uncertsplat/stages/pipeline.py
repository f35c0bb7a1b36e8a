"""Stage `pipeline` (issue 8)."""

from __future__ import annotations

from uncertsplat.errors import UserError


def run(*args, **kwargs):
    raise UserError("`pipeline` is not implemented yet (issue 8).")
