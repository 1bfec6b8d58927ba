"""Perception: frame sources, the leader detector, pinhole pose. Only ``detector`` imports torch."""
