"""adapt/schemes."""
