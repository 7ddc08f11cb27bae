"""Textbook bilevel problems with convex lower levels and published optimal values (registered on import).

Sources: Bard (1998) via the GAMS EMP library, MacMPEC (Leyffer) including the Floudas et al. (1999) ch. 9
models, BASBLib (Paulavičius et al.) and BOLIB (Zhou, Zemkoho & Tin 2020). Each builder's `source` names the
model file transcribed and the published value; every optimum is re-checked by brute force in
tests/problems/test_literature_data.py.

Tags "A-B" classify the upper objective (A) and the lower objective (B) jointly in (x, y): linear, quadratic
(including bilinear terms) or nonlinear; "nonlinear-convex" marks a lower level with a convex nonlinear
constraint. Further tags: "equality" (lower-level equalities), "max-lower"/"max-upper" (declared with
maximize_*), "nonunique-lower" (follower's response not unique at the solution; the optimistic convention
applies: the leader picks the follower response best for itself).
"""

from . import literature_bilinear, literature_linear, literature_nonlinear, literature_quadratic  # noqa: F401
