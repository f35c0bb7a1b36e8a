"""Stage `reconstruct` (issue 4)."""

from __future__ import annotations

from uncertsplat.errors import UserError


def run(*args, **kwargs):
    raise UserError("`reconstruct` is not implemented yet (issue 4).")
