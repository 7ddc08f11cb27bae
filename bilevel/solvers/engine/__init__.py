"""The machinery every method shares: the prepared problem and a method's run (prepared), implicit derivatives,
the ascent loop, projections, starts, the trust-region step, restoration, structure read from the declaration,
limits and option checks. It never imports a method, the verdict or the registry (tests/core/test_import_graph.py)."""
