"""Stage `prune` (issue 7)."""

from __future__ import annotations

from uncertsplat.errors import UserError


def run(*args, **kwargs):
    raise UserError("`prune` is not implemented yet (issue 7).")
