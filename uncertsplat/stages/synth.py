"""Stage `synth` (issue 2)."""

from __future__ import annotations

from uncertsplat.errors import UserError


def run(*args, **kwargs):
    raise UserError("`synth` is not implemented yet (issue 2).")
