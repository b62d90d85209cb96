"""Displacements in, density out: Poisson and least-squares integration of BOS displacement fields."""
