"""File I/O: images (OpenImageIO), atomic writes, checkpoints, PLY."""
