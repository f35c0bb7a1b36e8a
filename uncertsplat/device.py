"""Device selection: the only place that turns ``auto|cpu|cuda`` into a torch.device."""

from __future__ import annotations

import torch

from uncertsplat.errors import UserError


def resolve_device(name: str | torch.device) -> torch.device:
    """Map ``auto|cpu|cuda[:n]`` to a torch.device; a clear error when CUDA is asked for but absent."""
    if isinstance(name, torch.device):
        return name
    name = name.lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise UserError("--device cuda was requested but no CUDA device is available",
                            hint="Use --device cpu or --device auto.")
        return torch.device(name)
    raise UserError(f"unknown device '{name}'", hint="Use auto, cpu or cuda.")
