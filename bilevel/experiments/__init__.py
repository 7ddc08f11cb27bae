"""Experiments: solver comparisons, Monte Carlo sweeps and paper reproductions (results written as made)."""
