"""Training: the loop (``trainer``), one model trained into a run folder (``session``), losses and optimiser."""
