"""A run's result folder: its files, its ``summary.json``, its map PLYs and its lock."""
