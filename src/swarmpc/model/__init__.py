"""Dynamics and geometry: the bottom layer, plain numpy."""
