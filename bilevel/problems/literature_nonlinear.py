"""Literature problems with a convex NLP lower level (quartic, exponential or cubic terms, convex quadratic
constraints) or a lower constraint matrix that depends on x; method "global" proves them with algorithm "scip".

Transcribed from BOLIB (Zhou, Zemkoho & Tin 2020, "BOLIB: Bilevel Optimization LIBrary of test problems", in
Dempe & Zemkoho (eds.), Bilevel Optimization, Springer, pp. 563-580), as converted in BOLIB.jl (C. Inaral), and
checked against BASBLib (Paulavičius et al.) where it has the problem. BOLIB writes constraints as G(x, y) >= 0 and
g(x, y) >= 0; its value carries a flag: 1 optimal, 2 best known. Where BOLIB leaves an upper variable unbounded, a
box is declared that holds every feasible point or the optimum (the docstring says why): method "global" derives
multiplier bounds from a Slater point over that box. Every value is re-derived by hand in the docstring where the
follower's response has a closed form, and re-checked by brute force (a grid over x, the lower level solved
exactly at each point) in tests/problems/test_literature_data.py.
"""

from __future__ import annotations

import casadi as ca

from ..model import BilevelProblem
from .registry import register

_BOLIB = "BOLIB (Zhou, Zemkoho & Tin 2020; BOLIBver2, as converted in BOLIB.jl),"
_COLSON = "Colson (2002), 'BIPA (BIlevel Programming with Approximation methods): software guide and test problems', " \
          "Cahiers du GERAD G-2002-37"
_OUTRATA_1990 = "Outrata (1990), 'On the numerical solution of a class of Stackelberg problems', ZOR 34:255-277"


@register(
    "bolib-colson2002bipa1",
    source=f"{_BOLIB} Colson2002BIPA1, F* = 250, f* = 0 (flag 1: optimal); {_COLSON}, problem BIPA1 (BASBLib "
           "c_2002_01 drops the upper constraint x <= 5)",
    optimum=250.0, solution={"x": [5.0], "y": [5.0]}, lower_optimum=0.0,
    tags=("nonlinear-nonlinear", "convex-nlp", "textbook"))
def bolib_colson2002bipa1() -> BilevelProblem:
    """Cubic leader over a quartic follower min (x + 2y - 15)^4, whose response y = (15 - x)/2 is flat to fourth order.

    The upper constraint y <= x then needs x >= 5, and x <= 5 leaves x = y = 5: F* = 5^3 + 5^3 = 250.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=5)
    y = p.lower_variable("y", 1, lb=0, ub=20)
    p.minimize_upper((10 - x) ** 3 + (10 - y) ** 3)
    p.upper_constraint(y <= x)
    p.minimize_lower((x + 2 * y - 15) ** 4)
    p.lower_constraint(x + y <= 20)
    return p


@register(
    "bolib-colson2002bipa3",
    source=f"{_BOLIB} Colson2002BIPA3, F* = 2, f* = 24.02 (flag 2: best known; optimal by the docstring); {_COLSON}, "
           "problem BIPA3 (= BASBLib c_2002_03)",
    optimum=2.0, solution={"x": [4.0], "y": [0.0]}, lower_optimum=24.0 + float(ca.exp(-4.0)),
    tags=("nonlinear-nonlinear", "convex-nlp", "textbook"))
def bolib_colson2002bipa3() -> BilevelProblem:
    """Quartic leader over a follower with an exponential term, exp(y - x) + (x + y)^2 + 2x + 6y.

    Its derivative in y, exp(y - x) + 2(x + y) + 6, is positive for y >= 0, x >= 0: the follower plays y = 0, and
    F = (x - 5)^4 + 1 is smallest at the largest x, 4 (x + y <= 4): F* = 2. BOLIB bounds x below only; x + y <= 4 and
    y >= 0 give the declared x <= 4.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=4)
    y = p.lower_variable("y", 1, lb=0)
    p.minimize_upper((x - 5) ** 4 + (2 * y + 1) ** 4)
    p.upper_constraint(x + y <= 4)
    p.minimize_lower(2 * x + 6 * y + ca.exp(y - x) + 2 * x * y + x ** 2 + y ** 2)
    p.lower_constraint(y <= x + 2)
    return p


@register(
    "bolib-colson2002bipa4",
    source=f"{_BOLIB} Colson2002BIPA4, F* = 88.79, f* = -0.77 (flag 2: best known); {_COLSON}, problem BIPA4 "
           "(BASBLib c_2002_04 prints 88.754 at y = 0.579); exact optimum (10 - 1/sqrt(3))^2 at x = 0, y = 1/sqrt(3)",
    optimum=(10.0 - 3.0 ** -0.5) ** 2, solution={"x": [0.0], "y": [3.0 ** -0.5]},
    lower_optimum=2.0 / 3.0 ** 1.5 - 2.0 / 3.0 ** 0.5,
    tags=("quadratic-nonlinear", "convex-nlp", "textbook"))
def bolib_colson2002bipa4() -> BilevelProblem:
    """A cubic follower 2y^3 - 2y (convex on y >= 0) that always plays y = 1/sqrt(3); the leader takes x = 0.

    6y^2 = 2 gives y = 1/sqrt(3), inside 2y <= x + 3 for every x >= 0, so F = x^2 + (y - 10)^2 is smallest at x = 0:
    F* = (10 - 1/sqrt(3))^2 = 88.7863. BOLIB bounds x below only; x + 2y <= 6 and y >= 0 give the declared x <= 6.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=6)
    y = p.lower_variable("y", 1, lb=0)
    p.minimize_upper((y - 10) ** 2 + x ** 2)
    p.upper_constraint(x + 2 * y <= 6)
    p.minimize_lower(x - 2 * y - x ** 2 + x ** 3 + 2 * y ** 3)
    p.lower_constraint(2 * y <= x + 3)
    return p


@register(
    "bolib-colson2002bipa5",
    source=f"{_BOLIB} Colson2002BIPA5, F* = 2.75, f* = 0.57 (flag 2: best known); {_COLSON}, problem BIPA5 "
           "(= BASBLib c_2002_05, F* = 2.750 at x = 1.941, y = (0, 1.211))",
    optimum=2.74976764, solution={"x": [1.94050998], "y": [0.0, 1.21102988]}, lower_optimum=None,
    tags=("nonlinear-nonlinear", "nonlinear-convex", "convex-nlp", "textbook"), defaults={"x_ub": 2.2})
def bolib_colson2002bipa5(x_ub: float = 2.2) -> BilevelProblem:
    """Convex constraints exp(y2) + y1^2 + 6x <= 15 and y1^4 - y2 + 5x <= 25 on a strictly convex follower.

    The follower plays y1 = 0 and y2 = 3/2 while exp(3/2) <= 15 - 6x, then y2 = ln(15 - 6x); F = (x - y2)^4 + 1 + y2^2
    is smallest on the second branch, at x = 1.9405 (F* = 2.749768). The lower level is infeasible beyond x = 7/3;
    BOLIB bounds x below only, and the declared x <= 2.2 keeps a point strictly inside both convex constraints at
    every x (Slater's condition, which method "global" needs for its multiplier bounds); F >= 1 + (x - ln 1.8)^4 > 7
    on [2.2, 7/3], so the optimum is the same (the brute-force test covers [0, 7/3] with x_ub=7/3).
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=x_ub)
    y = p.lower_variable("y", 2, lb=0, ub=[4, 2])
    p.minimize_upper((x - y[1]) ** 4 + (y[0] - y[1]) ** 2 + (y[0] - 1) ** 2)
    p.minimize_lower(2 * x + 4 * y[0] - 6 * y[1] + ca.exp(y[0]) + y[0] ** 2 + 2 * y[1] ** 2)
    p.lower_constraint(ca.exp(y[1]) + y[0] ** 2 + 6 * x <= 15)
    p.lower_constraint(5 * x + y[0] ** 4 - y[1] <= 25)
    return p


@register(
    "bolib-allendestill2013",
    source=f"{_BOLIB} AllendeStill2013, F* = 1, f* = -0.5 (flag 1: optimal); Allende & Still (2013), 'Solving "
           "bilevel programs with the KKT-approach', Math. Program. 138:309-332",
    optimum=1.0, solution={"x": [0.5, 0.5], "y": [0.5, 0.5]}, lower_optimum=-0.5,
    tags=("quadratic-quadratic", "nonlinear-convex", "convex-nlp", "textbook"))
def bolib_allendestill2013() -> BilevelProblem:
    """The follower projects x onto two discs (y_i - 1)^2 <= 1/4, convex quadratic constraints.

    Each y_i = clip(x_i, 1/2, 3/2) and each coordinate adds (x_i - 1)^2 + y_i^2 >= 1/2, with equality at x_i = 1/2:
    F* = 1. BOLIB bounds x2 below only; F > 1 once x2 > 2, so the declared x2 <= 2 holds the optimum; the declared
    y in [0, 2] never binds (the discs keep y in [1/2, 3/2]) and gives the multiplier bound its range of f.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 2, lb=0, ub=2)
    y = p.lower_variable("y", 2, lb=0, ub=2)
    p.minimize_upper((x[0] - 1) ** 2 + (x[1] - 1) ** 2 + y[0] ** 2 + y[1] ** 2)
    p.minimize_lower(y[0] ** 2 + y[1] ** 2 - 2 * x[0] * y[0] - 2 * x[1] * y[1])
    p.lower_constraint((y[0] - 1) ** 2 <= 0.25)
    p.lower_constraint((y[1] - 1) ** 2 <= 0.25)
    return p


@register(
    "bolib-outrata1990ex2e",
    source=f"{_BOLIB} Outrata1990Ex2e, F* = 0.9, f* = -14.94 (flag 2: best known, rounded); {_OUTRATA_1990}, "
           "Example 2(e)",
    optimum=0.89745982, solution={"x": [3.99853521], "y": [1.66500895, 3.8872235]}, lower_optimum=None,
    tags=("quadratic-quadratic", "x-matrix", "textbook"), defaults={"x_ub": 10.0})
def bolib_outrata1990ex2e(x_ub: float = 10.0) -> BilevelProblem:
    """A strictly convex QP follower whose constraint rows (x/10 - 0.333) y1 + y2 <= x and y1 - (x/10 + 0.333) y2
    <= 2 and Hessian diag(1 + x, 1) depend on x; the leader wants y near (3, 4).

    BOLIB bounds x below only; the declared x <= 10 holds the optimum (x* = 3.998), and the brute-force test finds
    nothing better on [0, 20] (x_ub=20).
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=x_ub)
    y = p.lower_variable("y", 2, lb=0, ub=20)
    p.minimize_upper(0.5 * (y[0] - 3) ** 2 + 0.5 * (y[1] - 4) ** 2)
    p.minimize_lower(0.5 * (x + 1) * y[0] ** 2 - (1.333 * x + 3) * y[0] - x * y[1] + 0.5 * y[1] ** 2)
    p.lower_constraint((x / 10 - 0.333) * y[0] + y[1] <= x)
    p.lower_constraint(y[0] - (x / 10 + 0.333) * y[1] <= 2)
    return p


@register(
    "bolib-outrata1993ex31",
    source=f"{_BOLIB} Outrata1993Ex31, F* = 1.56, f* = -11.68 (flag 2: best known, rounded); Outrata (1993), "
           "'Necessary optimality conditions for Stackelberg problems', JOTA 76:305-320, Example 3.1",
    optimum=1.56287383, solution={"x": [1.90951797], "y": [2.97858787, 2.23215126]}, lower_optimum=None,
    tags=("quadratic-quadratic", "x-matrix", "textbook"), defaults={"x_ub": 10.0})
def bolib_outrata1993ex31(x_ub: float = 10.0) -> BilevelProblem:
    """Outrata's Example 2 with x also in the right-hand sides and in both diagonal Hessian entries.

    Rows (x/10 - 0.333) y1 + y2 <= 2 - x/10 and y1 - (x/10 + 0.333) y2 <= 2 - x/10; Hessian diag(x/5 + 1,
    x/10 + 1). BOLIB bounds x below only; the declared x <= 10 holds the optimum (x* = 1.91), and the brute-force
    test finds nothing better on [0, 20] (x_ub=20).
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=x_ub)
    y = p.lower_variable("y", 2, lb=0, ub=20)
    p.minimize_upper(0.5 * (y[0] - 3) ** 2 + 0.5 * (y[1] - 4) ** 2)
    p.minimize_lower((x / 10 + 0.5) * y[0] ** 2 - x * y[1] - (1.333 * x + 3) * y[0] + (x / 20 + 0.5) * y[1] ** 2)
    p.lower_constraint((x / 10 - 0.333) * y[0] + y[1] <= 2 - x / 10)
    p.lower_constraint(y[0] - (x / 10 + 0.333) * y[1] <= 2 - x / 10)
    return p


@register(
    "bolib-outrata1993ex32",
    source=f"{_BOLIB} Outrata1993Ex32, F* = 3.208, f* = -20.531 (flag 2: best known, rounded); Outrata (1993), "
           "'Necessary optimality conditions for Stackelberg problems', JOTA 76:305-320, Example 3.2",
    optimum=3.20770002, solution={"x": [4.06040643], "y": [2.68224443, 1.48714675]}, lower_optimum=None,
    tags=("quadratic-quadratic", "nonlinear-convex", "convex-nlp", "textbook"), defaults={"x_ub": 10.0})
def bolib_outrata1993ex32(x_ub: float = 10.0) -> BilevelProblem:
    """A convex quadratic constraint y1^2 + y2^2 <= 9 + x/10 and the row y2 - 0.333 y1 <= 1 - x/10 on Outrata's
    follower with Hessian diag(x/5 + 1, x/10 + 1).

    BOLIB bounds x below only; the declared x <= 10 holds the optimum (x* = 4.06), and the brute-force test finds
    nothing better on [0, 20] (x_ub=20); the declared y <= 4 never binds (the disc keeps |y| <= sqrt(10)) and gives the
    multiplier bound its range of f.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=x_ub)
    y = p.lower_variable("y", 2, lb=0, ub=4)
    p.minimize_upper(0.5 * (y[0] - 3) ** 2 + 0.5 * (y[1] - 4) ** 2)
    p.minimize_lower((x / 10 + 0.5) * y[0] ** 2 - x * y[1] - (1.333 * x + 3) * y[0] + (x / 20 + 0.5) * y[1] ** 2)
    p.lower_constraint(y[1] - 0.333 * y[0] <= 1 - x / 10)
    p.lower_constraint(y[0] ** 2 + y[1] ** 2 <= 9 + x / 10)
    return p
