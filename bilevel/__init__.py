"""bilevel: bilevel optimization with convex lower levels, certified."""
