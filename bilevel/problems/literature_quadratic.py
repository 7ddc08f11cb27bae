"""Literature problems with a quadratic (or convex-quadratically constrained) lower level.

Transcribed from the model files named in each `source`; published optimal values re-checked by brute force
(tests/problems/test_literature_data.py). Optimistic convention where the follower's response is not unique.
"""

from __future__ import annotations

from ..model import BilevelProblem
from .registry import register

_MACMPEC = "MacMPEC (S. Leyffer, AMPL collection of MPECs), model"
_FLOUDAS = "Floudas et al. (1999), Handbook of Test Problems in Local and Global Optimization, ch. 9"


@register(
    "macmpec-bard1",
    source=f"{_MACMPEC} bard1 (= ex9.2.1, ex9.2.7; {_FLOUDAS}); Bard (1988), Math. Program. 40:15-27, "
           "Example 1 (= BOLIB Bard1988Ex1, BASBLib b_1988_01)",
    optimum=17.0, solution={"x": [1.0], "y": [0.0]}, lower_optimum=1.0,
    tags=("quadratic-quadratic", "textbook"))
def macmpec_bard1() -> BilevelProblem:
    """Bard (1988) Example 1: quadratic leader, follower min (y-1)^2 - 1.5xy over three half-planes."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0)
    y = p.lower_variable("y", 1, lb=0)
    p.minimize_upper((x - 5) ** 2 + (2 * y + 1) ** 2)
    p.minimize_lower((y - 1) ** 2 - 1.5 * x * y)
    p.lower_constraint(-3 * x + y <= -3)
    p.lower_constraint(x - 0.5 * y <= 4)
    p.lower_constraint(x + y <= 7)
    return p


@register(
    "macmpec-ex9.2.2",
    source=f"{_MACMPEC} ex9.2.2 ({_FLOUDAS}); Shimizu & Aiyoshi (1981), IEEE TAC 26:460-466, Example 1 "
           "(= BOLIB ShimizuAiyoshi1981Ex1, BASBLib sa_1981_01)",
    optimum=100.0, solution={"x": [10.0], "y": [10.0]}, lower_optimum=0.0,
    tags=("quadratic-quadratic", "textbook"))
def macmpec_ex922() -> BilevelProblem:
    """Shimizu-Aiyoshi Example 1: the leader's constraint y <= x couples both levels."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=15)
    y = p.lower_variable("y", 1, lb=0, ub=20)
    p.minimize_upper(x ** 2 + (y - 10) ** 2)
    p.upper_constraint(-x + y <= 0)
    p.minimize_lower((x + 2 * y - 30) ** 2)
    p.lower_constraint(x + y <= 20)
    return p


@register(
    "macmpec-ex9.2.4",
    source=f"{_MACMPEC} ex9.2.4 ({_FLOUDAS}, test problem 9.3.5; GAMS EMP library flds924); Yezza (1996), "
           "JOTA 89:189-219, Example 4.1 (BOLIB Yezza1996Ex41 eliminates y2 = x - y1)",
    optimum=0.5, solution={"x": [3.0], "y": [1.0, 2.0]}, lower_optimum=2.5,
    tags=("quadratic-quadratic", "equality", "textbook"))
def macmpec_ex924() -> BilevelProblem:
    """Yezza Example 4.1: the follower splits x = y1 + y2 (lower-level equality) at cost y1^2/2 + y2."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0)
    y = p.lower_variable("y", 2, lb=0)
    p.minimize_upper(0.5 * (y[0] - 2) ** 2 + 0.5 * (y[1] - 2) ** 2)
    p.minimize_lower(0.5 * y[0] ** 2 + y[1])
    p.lower_constraint(y[0] + y[1] == x)
    return p


@register(
    "macmpec-ex9.2.5",
    source=f"{_MACMPEC} ex9.2.5 ({_FLOUDAS}); Clark & Westerberg (1990), Comput. Chem. Eng. 14:87-97, Sect. 3.2 "
           "(= BOLIB ClarkWesterberg1990a, BASBLib cw_1990_02)",
    optimum=5.0, solution={"x": [1.0], "y": [3.0]}, lower_optimum=4.0,
    tags=("quadratic-quadratic", "textbook"))
def macmpec_ex925() -> BilevelProblem:
    """Clark-Westerberg (1990) QP: the follower wants y = 5 but three x-dependent half-planes stop it."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=8)
    y = p.lower_variable("y", 1)
    p.minimize_upper((x - 3) ** 2 + (y - 2) ** 2)
    p.minimize_lower((y - 5) ** 2)
    p.lower_constraint(-2 * x + y <= 1)
    p.lower_constraint(x - 2 * y <= 2)
    p.lower_constraint(x + 2 * y <= 14)
    return p


@register(
    "macmpec-ex9.2.6",
    source=f"{_MACMPEC} ex9.2.6 and desilva ({_FLOUDAS}); De Silva (1978), PhD thesis, George Washington Univ., "
           "via Falk & Liu (1995), Math. Program. 70:47-72 (= BOLIB DeSilva1978, BASBLib d_1978_01)",
    optimum=-1.0, solution={"x": [0.5, 0.5], "y": [0.5, 0.5]}, lower_optimum=0.0,
    tags=("quadratic-quadratic", "textbook"))
def macmpec_ex926() -> BilevelProblem:
    """De Silva's problem: the follower projects x onto the box [0.5, 1.5]^2."""
    p = BilevelProblem()
    x = p.upper_variable("x", 2, lb=0)
    y = p.lower_variable("y", 2, lb=0.5, ub=1.5)
    p.minimize_upper(x[0] ** 2 - 2 * x[0] + x[1] ** 2 - 2 * x[1] + y[0] ** 2 + y[1] ** 2)
    p.minimize_lower((y[0] - x[0]) ** 2 + (y[1] - x[1]) ** 2)
    return p


@register(
    "macmpec-ex9.2.8",
    source=f"{_MACMPEC} ex9.2.8 ({_FLOUDAS}); Yezza (1996), JOTA 89:189-219, Example 3.1 (= BOLIB "
           "Yezza1996Ex31 with lower objective -(1-4x)y - 2x - 2, BASBLib y_1996_02)",
    optimum=1.5, solution={"x": [0.25], "y": [0.0]}, lower_optimum=-2.5,
    tags=("quadratic-quadratic", "nonunique-lower", "textbook"))
def macmpec_ex928() -> BilevelProblem:
    """Yezza Example 3.1: bilinear objectives; at the optimum x = 1/4 every y in [0, 1] is a follower optimum.

    The optimistic leader takes y = 0 there (F = 1.5); for x > 1/4 the follower plays y = 0 and F = 2x + 1,
    for x < 1/4 it plays y = 1 and F = 4 - 2x, so the infimum is attained only under the optimistic convention.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 1, lb=0, ub=1)
    p.minimize_upper(-(4 * x - 3) * y + 2 * x + 1)
    p.minimize_lower(-(1 - 4 * x) * y - 2 * x - 2)
    return p


@register(
    "macmpec-bard2",
    source=f"{_MACMPEC} bard2 / bilevel2 (MacMPEC lists 6598 and -6600); Bard (1988), Math. Program. 40:15-27, "
           "Example 2, from Aiyoshi & Shimizu (1981), IEEE Trans. SMC 11:444-449 (= BOLIB Bard1988Ex2, "
           "F* = -6600 in minimisation form, f* = 54)",
    optimum=6600.0, solution={"x": [7.0, 3.0, 12.0, 18.0], "y": [0.0, 10.0, 30.0, 0.0]}, lower_optimum=54.0,
    tags=("quadratic-quadratic", "max-upper", "textbook"))
def macmpec_bard2() -> BilevelProblem:
    """Resource allocation: the leader splits 40 units of two resources over two divisions to maximise revenue.

    x = (x11, x12, x21, x22) and y = (y11, y12, y21, y22). The two divisions are independent followers; as
    their problems do not interact, they are declared as one lower level with the summed (separable) objective.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 4, lb=0, ub=[10, 5, 15, 20])
    y = p.lower_variable("y", 4, lb=0, ub=[20, 20, 40, 40])
    p.maximize_upper((200 - y[0] - y[2]) * (y[0] + y[2]) + (160 - y[1] - y[3]) * (y[1] + y[3]))
    p.upper_constraint(x[0] + x[1] + x[2] + x[3] <= 40)
    p.minimize_lower((y[0] - 4) ** 2 + (y[1] - 13) ** 2 + (y[2] - 35) ** 2 + (y[3] - 2) ** 2)
    p.lower_constraint(0.4 * y[0] + 0.7 * y[1] <= x[0])
    p.lower_constraint(0.6 * y[0] + 0.3 * y[1] <= x[1])
    p.lower_constraint(0.4 * y[2] + 0.7 * y[3] <= x[2])
    p.lower_constraint(0.6 * y[2] + 0.3 * y[3] <= x[3])
    return p


@register(
    "macmpec-bard3",
    source=f"{_MACMPEC} bard3 / bilevel3 (-12.6787); Bard (1988), Math. Program. 40:15-27, Example 3 (= BOLIB "
           "Bard1988Ex3; BASBLib b_1984_02, Bard 1984 Example 2, which prints -12.687)",
    optimum=-12.6787109375, solution={"x": [0.0, 2.0], "y": [1.875, 0.90625]}, lower_optimum=-1.015625,
    tags=("nonlinear-quadratic", "textbook"))
def macmpec_bard3() -> BilevelProblem:
    """Bard's nonconvex example: concave-in-x leader with x1^2 + 2x2 <= 4, lower constraints nonlinear in x."""
    p = BilevelProblem()
    x = p.upper_variable("x", 2, lb=0)
    y = p.lower_variable("y", 2, lb=0)
    p.minimize_upper(-x[0] ** 2 - 3 * x[1] - 4 * y[0] + y[1] ** 2)
    p.upper_constraint(x[0] ** 2 + 2 * x[1] <= 4)
    p.minimize_lower(2 * x[0] ** 2 + y[0] ** 2 - 5 * y[1])
    p.lower_constraint(-x[0] ** 2 + 2 * x[0] - x[1] ** 2 + 2 * y[0] - y[1] - 3 <= 0)
    p.lower_constraint(-x[1] - 3 * y[0] + 4 * y[1] + 4 <= 0)
    return p


@register(
    "bard1998-ex7.2.2",
    source="Bard (1998), Practical Bilevel Optimization, Example 7.2.2, p. 281, as in GAMS EMP library model "
           "bard722 (lower term -y; BASBLib b_1998_03 notes the sign)",
    optimum=0.0, solution={"x": [1.0, 0.4], "y": [0.8]}, lower_optimum=-0.32,
    tags=("quadratic-quadratic", "textbook"))
def bard1998_ex722() -> BilevelProblem:
    """Bard's unit-box QP: two leader variables steer a scalar follower to the leader's ideal point."""
    p = BilevelProblem()
    x = p.upper_variable("x", 2, lb=0, ub=1)
    y = p.lower_variable("y", 1, lb=0, ub=1)
    p.minimize_upper(0.5 * (x[0] - 1) ** 2 + 0.5 * (x[1] - 0.4) ** 2 + 0.5 * (y - 0.8) ** 2)
    p.minimize_lower(0.5 * y ** 2 - y - x[0] * y + 3 * x[1] * y)
    return p


@register(
    "bard1998-ex8.5.1",
    source="Bard (1998), Practical Bilevel Optimization, Example 8.5.1, p. 336, as in GAMS EMP library model "
           "bard851 (= BASBLib b_1998_07); solution x = 17/9, y = (8/9, 0), F* = -38/27",
    optimum=-38.0 / 27.0, solution={"x": [17.0 / 9.0], "y": [8.0 / 9.0, 0.0]}, lower_optimum=617.0 / 81.0,
    tags=("quadratic-quadratic", "textbook"))
def bard1998_ex851() -> BilevelProblem:
    """Bard's QP with four lower half-planes whose feasible set pinches to one point at the optimum."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0)
    y = p.lower_variable("y", 2, lb=0)
    p.minimize_upper((x - 1) ** 2 + 2 * y[0] ** 2 - 2 * x)
    p.minimize_lower((2 * y[0] - 4) ** 2 + (2 * y[1] - 1) ** 2 + x * y[0])
    p.lower_constraint(4 * x + 5 * y[0] + 4 * y[1] <= 12)
    p.lower_constraint(-4 * x - 5 * y[0] + 4 * y[1] <= -4)
    p.lower_constraint(4 * x - 4 * y[0] + 5 * y[1] <= 4)
    p.lower_constraint(-4 * x + 4 * y[0] + 5 * y[1] <= 4)
    return p


@register(
    "bolib-macalhurter1997",
    source="BOLIB MacalHurter1997 (Zhou, Zemkoho & Tin 2020; F* = 81.33, f* = -0.33); Bard (1998), Example 8.1.3 "
           "(= BASBLib b_1998_04, x* = 10.02, y* = 0.82); exact optimum 203401/2501 at x = 25051/2501",
    optimum=203401.0 / 2501.0, solution={"x": [25051.0 / 2501.0], "y": [2050.0 / 2501.0]},
    lower_optimum=-0.5 * (2050.0 / 2501.0) ** 2,
    tags=("quadratic-quadratic", "textbook"))
def bolib_macalhurter1997() -> BilevelProblem:
    """Unconstrained QP follower y = 50x - 500; the leader trades off (x-1)^2 against (y-1)^2."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1)
    y = p.lower_variable("y", 1)
    p.minimize_upper((x - 1) ** 2 + (y - 1) ** 2)
    p.minimize_lower(0.5 * y ** 2 + 500 * y - 50 * x * y)
    return p


@register(
    "bolib-hendersonquandt1958",
    source="BOLIB HendersonQuandt1958 (Zhou, Zemkoho & Tin 2020; F* = -3266.7 at (93.333, 26.667)); Henderson & "
           "Quandt (1958), Microeconomic Theory (Stackelberg duopoly); exact F* = -9800/3 at x = 280/3, y = 80/3",
    optimum=-9800.0 / 3.0, solution={"x": [280.0 / 3.0], "y": [80.0 / 3.0]}, lower_optimum=-(80.0 / 3.0) ** 2,
    tags=("quadratic-quadratic", "textbook"))
def bolib_hendersonquandt1958() -> BilevelProblem:
    """Stackelberg duopoly: leader output x in [0, 200], follower output y >= 0, linear inverse demand."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=200)
    y = p.lower_variable("y", 1, lb=0)
    p.minimize_upper((0.5 * (x + y) - 95) * x)
    p.minimize_lower((y + 0.5 * x - 100) * y)
    return p


@register(
    "bolib-gumusfloudas2001ex4",
    source="BOLIB GumusFloudas2001Ex4 (Zhou, Zemkoho & Tin 2020; F* = 9); Gumus & Floudas (2001), J. Glob. Optim. "
           "20:1-31, Example 4; from Sahin & Ciric (1998), Comput. Chem. Eng. 23:11-25, Example 3 "
           "(= BASBLib sc_1998_01)",
    optimum=9.0, solution={"x": [3.0], "y": [5.0]}, lower_optimum=0.0,
    tags=("quadratic-quadratic", "textbook"))
def bolib_gumusfloudas2001ex4() -> BilevelProblem:
    """Clark-Westerberg's half-planes moved to the upper level: the follower reaches y = 5, F* = 9 (not 5)."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=8)
    y = p.lower_variable("y", 1, lb=0, ub=10)
    p.minimize_upper((x - 3) ** 2 + (y - 2) ** 2)
    p.upper_constraint(-2 * x + y - 1 <= 0)
    p.upper_constraint(x - 2 * y + 2 <= 0)
    p.upper_constraint(x + 2 * y - 14 <= 0)
    p.minimize_lower((y - 5) ** 2)
    return p


@register(
    "bolib-floudaszlobec1998",
    source="BOLIB FloudasZlobec1998 (Zhou, Zemkoho & Tin 2020; F* = 1, f* = -1); Floudas & Zlobec (1998), in "
           "Migdalas et al. (eds.), Multilevel Optimization, Kluwer; Gumus & Floudas (2001), Example 2 "
           "(= BASBLib fz_1998_01)",
    optimum=1.0, solution={"x": [1.0], "y": [0.0, 1.0]}, lower_optimum=-1.0,
    tags=("nonlinear-convex", "textbook"))
def bolib_floudaszlobec1998() -> BilevelProblem:
    """Cubic leader x^3 y1 + y2; the follower maximises y2 under the convex constraint y1^2 + x y2 <= 1."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0, ub=1)
    y = p.lower_variable("y", 2, lb=[-1, 0], ub=[1, 100])
    p.minimize_upper(x ** 3 * y[0] + y[1])
    p.minimize_lower(-y[1])
    p.lower_constraint(x * y[0] <= 10)
    p.lower_constraint(y[0] ** 2 + x * y[1] <= 1)
    return p
