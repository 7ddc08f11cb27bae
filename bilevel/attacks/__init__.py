"""Data-poisoning attacks on data-driven control learners (VRFT, De Persis–Tesi), built on the bilevel core."""
