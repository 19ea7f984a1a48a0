"""Costs, OBCA constraints and the optimal-control problems, built in CasADi."""
