"""Pictures (PNG, matplotlib): before/after previews, contact sheets of frames, weight maps."""
