"""uncertsplat: photos to a calibrated uncertainty report for variational multi-scale 3DGS."""

__version__ = "0.1.0"
