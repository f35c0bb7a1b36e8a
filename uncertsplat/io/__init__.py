"""File I/O: images (OpenImageIO), atomic writes, checkpoints, PLY, the layout of evaluate's maps (``maps``).

Loading a whole run folder (config, scene, model) is ``baselines.load_run``'s.
"""
