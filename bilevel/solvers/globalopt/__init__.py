"""Method "global" (method.py) and its parts: the MPCC as numeric data (form), derived big-M bounds (bigm, slater),
node relaxations (nodes), branch-and-bound (bb), the MILP (milp) and SCIP (scip) routes."""
