"""Literature problems whose leader is nonconvex (bilinear or polynomial upper objective: tolls or prices times
flows) over a linear lower level; method "global" proves them with algorithm "scip".

Transcribed from BOLIB (Zhou, Zemkoho & Tin 2020, "BOLIB: Bilevel Optimization LIBrary of test problems", in
Dempe & Zemkoho (eds.), Bilevel Optimization, Springer, pp. 563-580), as converted in BOLIB.jl (C. Inaral); BOLIB
writes constraints as G(x, y) >= 0 and g(x, y) >= 0, and each lower equality as two inequalities (declared here as
an equality). Where BOLIB leaves a leader variable of a bilinear term unbounded, a box is declared that holds the
optimum (the docstring says why), so the optimal value is BOLIB's; method "global" needs finite bounds on the
variables of nonconvex terms. Maximised revenues are declared with maximize_upper, so `optimum` is BOLIB's F*
with the sign flipped. BOLIB tabulates a value with a flag: 1 optimal, 2 best known. Every value below is re-derived by
hand in its docstring (path enumeration for the toll problems) and re-checked by brute force over the lower
level's vertices in tests/solvers/test_global_scip.py. Optimistic convention where the follower's response is not
unique (the toll problems' optima all have a tie the leader breaks).
"""

from __future__ import annotations

from ..model import BilevelProblem
from .registry import register

_BOLIB = "BOLIB (Zhou, Zemkoho & Tin 2020; BOLIBver2, as converted in BOLIB.jl),"


@register(
    "bolib-lucchettietal1987",
    source=f"{_BOLIB} LucchettiEtal1987, F* = 0, f* = 0 (flag 1: optimal); Lucchetti, Mignanego & Pieri (1987), "
           "'Existence theorems of equilibrium points in Stackelberg games with constraints', Optimization "
           "18:857-866",
    optimum=0.0, solution={"x": [1.0], "y": [0.0]}, lower_optimum=0.0,
    tags=("bilinear", "quadratic-quadratic", "nonunique-lower", "textbook"))
def bolib_lucchettietal1987() -> BilevelProblem:
    """Bilinear leader x*y over an LP follower that plays y = 1 for x < 1 and is indifferent at x = 1.

    For x < 1 the follower's cost y(x - 1) is minimised by y = 1, giving F = x/2 + 1/2 >= 1/2; at x = 1 every y in
    [0, 1] is optimal and the optimistic leader takes y = 0, F = 0.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 1, lb=0, ub=1)
    p.minimize_upper(x * y - x / 2 + 0.5)
    p.minimize_lower(y * (x - 1))
    return p


@register(
    "bolib-ishizukaaiyoshi1992a",
    source=f"{_BOLIB} IshizukaAiyoshi1992a, F* = 0, f* = -1.5 (flag 1: optimal); Ishizuka & Aiyoshi (1992), "
           "'Double penalty method for bilevel optimization problems', Ann. Oper. Res. 34:73-88",
    optimum=0.0, solution={"x": [1.5], "y": [-1.5, 0.0]}, lower_optimum=-1.5,
    tags=("polynomial", "nonlinear-linear", "nonunique-lower", "textbook"))
def bolib_ishizukaaiyoshi1992a() -> BilevelProblem:
    """Cubic leader x*y2^2 over an LP follower (min y1 on |y1| <= x, |y1 + y2| <= 3/2) that ignores y2.

    The follower plays y1 = -x, and any y2 in [x - 3/2, x + 3/2]. BOLIB's lower constraint x >= 0 (no y in it:
    the follower is infeasible for x < 0) is the bound lb = 0 here, which also makes BOLIB's upper constraint
    x >= -3/2 redundant; so F >= 0, and F = 0 with y2 = 0 for every x in [0, 3/2] (BOLIB's point is x = 3/2, where
    f = -3/2). The declared ub = 10 holds that optimum.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=10)
    y = p.lower_variable("y", 2)
    p.minimize_upper(x * y[1] ** 2)
    p.minimize_lower(y[0])
    p.lower_constraint(x + y[0] >= 0)
    p.lower_constraint(x - y[0] >= 0)
    p.lower_constraint(y[0] + y[1] >= -1.5)
    p.lower_constraint(y[0] + y[1] <= 1.5)
    return p


@register(
    "bolib-tollsettingp1",
    source=f"{_BOLIB} TollSettingP1, F* = -7, f* = 12 (flag 2: best known; optimal by path enumeration, see the "
           "docstring); the toll-setting model of Labbé, Marcotte & Savard (1998), 'A bilevel model of taxation and "
           "its application to optimal highway pricing', Management Science 44(12):1608-1622",
    optimum=7.0, solution={"x": [7.0, 12.0, 12.0], "y": [0, 0, 1, 0, 0, 0, 0, 0]}, lower_optimum=12.0,
    tags=("bilinear", "toll", "quadratic-quadratic", "max-upper", "nonunique-lower", "textbook"))
def bolib_tollsettingp1() -> BilevelProblem:
    """Toll setting on a 5-node network: the leader maximises toll revenue on three arcs, one unit of traffic takes
    the cheapest path (LP on arc flows y1..y8 with flow conservation).

    Path costs: direct tolled arc 5 + x1; toll-free 12; 4 + x2 + x3; 6 + x3; 8 + x3; 8 + x2. Revenue on the
    direct arc is at most 12 - 5 = 7; any path through x3 earns at most 6 (6 + x3 <= 12, and x2 <= 2 where
    4 + x2 + x3 <= 6 + x3); so F* = -7 at x1 = 7 (the follower ties with the toll-free path and the optimistic
    convention sends the traffic on the tolled arc). BOLIB leaves the tolls unbounded above; the declared ub = 12
    (the toll-free path's cost) holds the optimum: x = (7, 12, 12), for instance.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 3, lb=0, ub=12)
    y = p.lower_variable("y", 8, lb=0)
    p.maximize_upper(x[0] * y[2] + x[1] * y[3] + x[2] * y[7])
    p.minimize_lower(2 * y[0] + 6 * y[1] + (5 + x[0]) * y[2] + x[1] * y[3] + 4 * y[4] + 2 * y[5] + 6 * y[6]
                     + x[2] * y[7])
    p.lower_constraint(y[0] + y[1] + y[2] == 1)            # origin
    p.lower_constraint(y[0] - y[3] - y[4] == 0)
    p.lower_constraint(y[1] + y[3] - y[5] - y[6] == 0)
    p.lower_constraint(y[4] + y[5] - y[7] == 0)
    p.lower_constraint(y[2] + y[6] + y[7] == 1)            # destination
    return p


@register(
    "bolib-tollsettingp4",
    source=f"{_BOLIB} TollSettingP4, F* = -4, f* = 14 (flag 2: best known; optimal by enumeration, see the "
           "docstring); toll setting after Labbé, Marcotte & Savard (1998), Management Science 44(12):1608-1622",
    optimum=4.0, solution={"x": [2.5, -1.0], "y": [0, 1, 1, 0]}, lower_optimum=14.0,
    tags=("bilinear", "toll", "quadratic-quadratic", "max-upper", "nonunique-lower", "textbook"))
def bolib_tollsettingp4() -> BilevelProblem:
    """Two commodities, each choosing a toll-free arc (cost 8, resp. 6) or a tolled one (3 + 2 x1, resp.
    3 + 2 x1 + 2 x2); x2 may be negative (a subsidy).

    Both tolled: x1 <= 5/2 and x1 + x2 <= 3/2, revenue 2 x1 + x2 <= 4 at x = (5/2, -1); one commodity only earns
    at most 5/2; so F* = -4. BOLIB leaves x free; the declared box [-10, 10]^2 holds the optimum.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 2, lb=-10, ub=10)
    y = p.lower_variable("y", 4, lb=0)
    p.maximize_upper(x[0] * (y[1] + y[2]) + x[1] * y[2])
    p.minimize_lower(8 * y[0] + 6 * y[3] + (2 * x[0] + 3) * y[1] + (2 * x[0] + 2 * x[1] + 3) * y[2])
    p.lower_constraint(y[0] + y[1] == 1)
    p.lower_constraint(y[2] + y[3] == 1)
    return p


@register(
    "bolib-tollsettingp5",
    source=f"{_BOLIB} TollSettingP5, F* = -2.5, f* = 14 (flag 2: best known; optimal by enumeration, see the "
           "docstring); toll setting after Labbé, Marcotte & Savard (1998), Management Science 44(12):1608-1622",
    optimum=2.5, solution={"x": [2.5], "y": [0, 1, 0, 1]}, lower_optimum=14.0,
    tags=("bilinear", "toll", "quadratic-quadratic", "max-upper", "nonunique-lower", "textbook"))
def bolib_tollsettingp5() -> BilevelProblem:
    """One toll on two commodities' tolled arcs (cost 3 + 2x, resp. 4 + 2x, against toll-free 8, resp. 6).

    x <= 1 tolls both (revenue 2x <= 2); 1 < x <= 5/2 only the first (revenue x <= 5/2): F* = -2.5 at x = 5/2.
    BOLIB leaves x free; the declared box [-10, 10] holds the optimum.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=-10, ub=10)
    y = p.lower_variable("y", 4, lb=0)
    p.maximize_upper(x * (y[1] + y[2]))
    p.minimize_lower(8 * y[0] + 6 * y[3] + (2 * x + 3) * y[1] + (2 * x + 4) * y[2])
    p.lower_constraint(y[0] + y[1] == 1)
    p.lower_constraint(y[2] + y[3] == 1)
    return p
