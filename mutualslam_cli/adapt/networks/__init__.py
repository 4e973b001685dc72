"""adapt/networks."""
