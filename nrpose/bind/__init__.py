"""Rest-only work done once per character: handle distances, weights, and their disk cache."""
