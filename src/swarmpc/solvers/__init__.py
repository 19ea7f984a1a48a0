"""Numerical solvers and initial-guess strategies."""
