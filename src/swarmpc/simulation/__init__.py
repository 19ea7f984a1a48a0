"""Receding-horizon simulation: the closed loop, metrics and run folders."""
