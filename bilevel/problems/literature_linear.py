"""Literature problems whose lower level is a linear program in y (linear-linear and linear-quadratic).

Every instance is transcribed from the model file named in its `source` (MacMPEC AMPL models by S. Leyffer,
the GAMS EMP library, BASBLib by Paulavičius et al., BOLIB by Zhou, Zemkoho & Tin) and its published optimal
value was re-checked by brute force (tests/problems/test_literature_data.py). Optimistic convention throughout:
where the follower has several optimal responses, the leader gets the one that is best for it.
"""

from __future__ import annotations

from ..model import BilevelProblem
from .registry import register

_MACMPEC = "MacMPEC (S. Leyffer, AMPL collection of MPECs), model"
_FLOUDAS = "Floudas et al. (1999), Handbook of Test Problems in Local and Global Optimization, ch. 9"


@register(
    "bard1998-ex5.1.1",
    source="Bard (1998), Practical Bilevel Optimization, Example 5.1.1, p. 197 (GAMS EMP library model bard511; "
           "also Shimizu, Ishizuka & Bard (1997), Example 16.1.1 = BASBLib sib_1997_02)",
    optimum=-12.0, solution={"x": [4.0], "y": [4.0]}, lower_optimum=4.0,
    tags=("linear-linear", "textbook"))
def bard1998_ex511() -> BilevelProblem:
    """Bard's textbook linear bilevel program: min x - 4y, follower minimises y over 4 half-planes."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0)
    y = p.lower_variable("y", 1, lb=0)
    p.minimize_upper(x - 4 * y)
    p.minimize_lower(y)
    p.lower_constraint(-x - y <= -3)
    p.lower_constraint(-2 * x + y <= 0)
    p.lower_constraint(2 * x + y <= 12)
    p.lower_constraint(3 * x - 2 * y <= 4)
    return p


@register(
    "macmpec-ex9.1.1",
    source=f"{_MACMPEC} ex9.1.1 ({_FLOUDAS}, test problem 9.2.2); Clark & Westerberg (1990), Comput. Chem. Eng. "
           "14:87-97, Sect. 3.1 'multiple inner problem maxima' (= BASBLib cw_1990_01 with y2 unbounded)",
    optimum=-13.0, solution={"x": [5.0], "y": [4.0, 2.0]}, lower_optimum=4.0,
    tags=("linear-linear", "max-lower", "nonunique-lower", "textbook"))
def macmpec_ex911() -> BilevelProblem:
    """Clark-Westerberg LP whose follower maximises y1 only, leaving y2 free (optimistic choice needed).

    At x = 5 every y2 in [2, 5.5] is optimal for the follower (y1 = 4); the optimistic leader takes y2 = 2
    and gets F = -13, the pessimistic one would get -6. A local KKT solve may stop at x = 6, y = (4, 6),
    F = -6 (the solution reported in the GAMS EMP model flds911).
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0)
    y = p.lower_variable("y", 2)
    p.minimize_upper(-x - 3 * y[0] + 2 * y[1])
    p.maximize_lower(y[0])
    p.lower_constraint(-2 * x + y[0] + 4 * y[1] <= 16)
    p.lower_constraint(8 * x + 3 * y[0] - 2 * y[1] <= 48)
    p.lower_constraint(-2 * x + y[0] - 3 * y[1] <= -12)
    p.lower_constraint(-y[0] <= 0)
    p.lower_constraint(y[0] <= 4)
    return p


@register(
    "macmpec-ex9.1.3",
    source=f"{_MACMPEC} ex9.1.3 ({_FLOUDAS}); Candler & Townsley (1982), Comput. Oper. Res. 9:59-76, Sect. 6 "
           "(= BASBLib ct_1982_01)",
    optimum=-29.2, solution={"x": [0.0, 0.9], "y": [0.0, 0.6, 0.4, 0.0, 0.0, 0.0]}, lower_optimum=1.4,
    tags=("linear-linear", "equality", "textbook"))
def macmpec_ex913() -> BilevelProblem:
    """Candler-Townsley LP in standard form: 3 lower equalities with slacks y4..y6 >= 0, 2 leader variables."""
    p = BilevelProblem()
    x = p.upper_variable("x", 2, lb=0)
    y = p.lower_variable("y", 6, lb=0)
    p.minimize_upper(4 * y[0] - 40 * y[1] - 4 * y[2] - 8 * x[0] - 4 * x[1])
    p.minimize_lower(y[0] + y[1] + 2 * y[2])
    p.lower_constraint(-y[0] + y[1] + y[2] + y[3] == 1)
    p.lower_constraint(-y[0] + 2 * y[1] - 0.5 * y[2] + y[4] + 2 * x[0] == 1)
    p.lower_constraint(2 * y[0] - y[1] - 0.5 * y[2] + y[5] + 2 * x[1] == 1)
    return p


@register(
    "macmpec-ex9.1.4",
    source=f"{_MACMPEC} ex9.1.4 ({_FLOUDAS}); Clark & Westerberg (1988), Naval Res. Logist. 35:413-418 "
           "(= BASBLib cw_1988_01)",
    optimum=-37.0, solution={"x": [19.0], "y": [14.0]}, lower_optimum=14.0,
    tags=("linear-linear", "textbook"))
def macmpec_ex914() -> BilevelProblem:
    """Clark-Westerberg (1988) LP: min x - 4y, follower minimises y over three half-planes."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0)
    y = p.lower_variable("y", 1, lb=0)
    p.minimize_upper(x - 4 * y)
    p.minimize_lower(y)
    p.lower_constraint(-2 * x + y <= 0)
    p.lower_constraint(2 * x + 5 * y <= 108)
    p.lower_constraint(2 * x - 3 * y <= -4)
    return p


@register(
    "macmpec-ex9.1.5",
    source=f"{_MACMPEC} ex9.1.5 ({_FLOUDAS}); Bard (1991), JOTA 68:371-378, Example 2.2 (= BASBLib b_1991_01, "
           "which notes F* = -1, not the +1 printed in Bard 1998)",
    optimum=-1.0, solution={"x": [0.0], "y": [0.0, 1.0]}, lower_optimum=-1.0,
    tags=("linear-linear", "nonunique-lower", "textbook"))
def macmpec_ex915() -> BilevelProblem:
    """Bard's ambiguous LP: the follower's response is unique only at x = 1; F* = -1 at x = 0 and at x = 1.

    At the registered solution x = 0 every y with y1 + y2 = 1 is optimal for the follower; the optimistic
    leader takes y = (0, 1). The other optimum x = 1, y = (0, 0) has a unique follower response.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0)
    y = p.lower_variable("y", 2, lb=0)
    p.minimize_upper(-x + 10 * y[0] - y[1])
    p.minimize_lower(-y[0] - y[1])
    p.lower_constraint(x + y[0] <= 1)
    p.lower_constraint(x + y[1] <= 1)
    p.lower_constraint(y[0] + y[1] <= 1)
    return p


@register(
    "macmpec-ex9.1.6",
    source=f"{_MACMPEC} ex9.1.6 ({_FLOUDAS}); Anandalingam & White (1990), IEEE TAC 35:1170-1173, Example E1 "
           "(from Bialas & Karwan 1982; = BASBLib aw_1990_01)",
    optimum=-49.0, solution={"x": [16.0], "y": [11.0]}, lower_optimum=17.0,
    tags=("linear-linear", "textbook"))
def macmpec_ex916() -> BilevelProblem:
    """Anandalingam-White LP with five lower constraints: min -x - 3y, follower minimises -x + 3y."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0)
    y = p.lower_variable("y", 1, lb=0)
    p.minimize_upper(-x - 3 * y)
    p.minimize_lower(-x + 3 * y)
    p.lower_constraint(-x - 2 * y <= -10)
    p.lower_constraint(x - 2 * y <= 6)
    p.lower_constraint(2 * x - y <= 21)
    p.lower_constraint(x + 2 * y <= 38)
    p.lower_constraint(-x + 2 * y <= 18)
    return p


@register(
    "macmpec-ex9.1.7",
    source=f"{_MACMPEC} ex9.1.7 ({_FLOUDAS}); Bard & Falk (1982), Comput. Oper. Res. 9:77-100, Example 1 "
           "(= BASBLib bf_1982_01)",
    optimum=-26.0, solution={"x": [0.0, 0.9], "y": [0.0, 0.6, 0.4]}, lower_optimum=3.2,
    tags=("linear-linear", "textbook"))
def macmpec_ex917() -> BilevelProblem:
    """Bard-Falk Example 1: 2 leader and 3 follower variables, three coupled lower constraints."""
    p = BilevelProblem()
    x = p.upper_variable("x", 2, lb=0)
    y = p.lower_variable("y", 3, lb=0)
    p.minimize_upper(-8 * x[0] - 4 * x[1] + 4 * y[0] - 40 * y[1] + 4 * y[2])
    p.minimize_lower(x[0] + 2 * x[1] + y[0] + y[1] + 2 * y[2])
    p.lower_constraint(-y[0] + y[1] + y[2] <= 1)
    p.lower_constraint(2 * x[0] - y[0] + 2 * y[1] - 0.5 * y[2] <= 1)
    p.lower_constraint(2 * x[1] + 2 * y[0] - y[1] - 0.5 * y[2] <= 1)
    return p


@register(
    "macmpec-ex9.1.8",
    source=f"{_MACMPEC} ex9.1.8 ({_FLOUDAS}); Bard & Falk (1982), Comput. Oper. Res. 9:77-100, Example 2; "
           "lower objective as in BASBLib bf_1982_02 (the MacMPEC KKT row kt2 has a sign slip)",
    optimum=-3.25, solution={"x": [2.0, 0.0], "y": [1.5, 0.0]}, lower_optimum=-4.0,
    tags=("linear-linear", "textbook"))
def macmpec_ex918() -> BilevelProblem:
    """Bard-Falk Example 2: two leader variables with an upper-level budget x1 + x2 <= 2."""
    p = BilevelProblem()
    x = p.upper_variable("x", 2, lb=0)
    y = p.lower_variable("y", 2, lb=0)
    p.minimize_upper(-2 * x[0] + x[1] + 0.5 * y[0])
    p.upper_constraint(x[0] + x[1] <= 2)
    p.minimize_lower(x[0] + x[1] - 4 * y[0] + y[1])
    p.lower_constraint(-2 * x[0] + y[0] - y[1] <= -2.5)
    p.lower_constraint(x[0] - 3 * x[1] + y[1] <= 2)
    return p


@register(
    "macmpec-ex9.1.9",
    source=f"{_MACMPEC} ex9.1.9 ({_FLOUDAS}); Bard (1984), Naval Res. Logist. Q. 31:13-26, Example 1 "
           "(= BASBLib b_1984_01); F* = 28/9 = 3.11111",
    optimum=28.0 / 9.0, solution={"x": [8.0 / 9.0], "y": [20.0 / 9.0]}, lower_optimum=-60.0 / 9.0,
    tags=("linear-linear", "textbook"))
def macmpec_ex919() -> BilevelProblem:
    """Bard (1984) LP: min x + y while the follower pushes y up (min -5x - y) over four half-planes."""
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=0)
    y = p.lower_variable("y", 1, lb=0)
    p.minimize_upper(x + y)
    p.minimize_lower(-5 * x - y)
    p.lower_constraint(-x - 0.5 * y <= -2)
    p.lower_constraint(-0.25 * x + y <= 2)
    p.lower_constraint(x + 0.5 * y <= 8)
    p.lower_constraint(x - 2 * y <= 2)
    return p


@register(
    "macmpec-bilevel1",
    source=f"{_MACMPEC} bilevel1 (Facchinei, Jiang & Qi 1996, problem 7); Aiyoshi & Shimizu (1984), IEEE TAC "
           "29:1111-1114, Example 2 (= BASBLib as_1984_01, F* = 0 at x = (0, 30), y = (-10, 10)); BOLIB "
           "AiyoshiShimizu1984Ex2 lists F* = 5 at x = (25, 30), which is not optimal",
    optimum=0.0, solution={"x": [0.0, 30.0], "y": [-10.0, 10.0]}, lower_optimum=100.0,
    tags=("linear-quadratic", "textbook"))
def macmpec_bilevel1() -> BilevelProblem:
    """Aiyoshi-Shimizu: linear leader with a coupling constraint, follower tracks x - 20 inside a box.

    The optimum F* = 0 is attained at several leader decisions, e.g. x = (0, 30) and x = (0, 0).
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 2, lb=0, ub=50)
    y = p.lower_variable("y", 2)
    p.minimize_upper(2 * x[0] + 2 * x[1] - 3 * y[0] - 3 * y[1] - 60)
    p.upper_constraint(x[0] + x[1] + y[0] - 2 * y[1] - 40 <= 0)
    p.minimize_lower((y[0] - x[0] + 20) ** 2 + (y[1] - x[1] + 20) ** 2)
    p.lower_constraint(y[0] >= -10)
    p.lower_constraint(y[0] <= 20)
    p.lower_constraint(y[1] >= -10)
    p.lower_constraint(y[1] <= 20)
    p.lower_constraint(x[0] - 2 * y[0] - 10 >= 0)
    p.lower_constraint(x[1] - 2 * y[1] - 10 >= 0)
    return p


@register(
    "macmpec-ex9.2.9",
    source=f"{_MACMPEC} ex9.2.9 ({_FLOUDAS}); Bard (1991), JOTA 68:371-378, Example 2.1 (= BOLIB Bard1991Ex1, "
           "BASBLib b_1991_02)",
    optimum=2.0, solution={"x": [2.0], "y": [6.0, 0.0]}, lower_optimum=12.0,
    tags=("linear-quadratic", "nonunique-lower", "textbook"))
def macmpec_ex929() -> BilevelProblem:
    """Bard (1991) Example 2.1: the follower's LP cost x*y2 ties with 2*y1 exactly at the optimum x = 2.

    At x = 2 every y with y1 + y2 = 6 is optimal for the follower; the optimistic leader takes y2 = 0.
    """
    p = BilevelProblem()
    x = p.upper_variable("x", 1, lb=2, ub=4)
    y = p.lower_variable("y", 2, lb=0)
    p.minimize_upper(x + y[1])
    p.minimize_lower(2 * y[0] + x * y[1])
    p.lower_constraint(x - y[0] - y[1] <= -4)
    return p



def _savard_lower(p: BilevelProblem) -> tuple:
    """Variables, coupling constraint and follower of the Savard / Hansen-Jaumard-Savard linear example."""
    x = p.upper_variable("x", 2, lb=0)
    y = p.lower_variable("y", 3, lb=0)
    p.upper_constraint(x[0] + 2 * x[1] - y[2] <= 1.3)
    p.minimize_lower(2 * y[0] + y[1] + 2 * y[2])
    p.lower_constraint(-y[0] + y[1] + y[2] <= 1)
    p.lower_constraint(4 * x[0] - 2 * y[0] + 4 * y[1] - y[2] <= 2)
    p.lower_constraint(4 * x[1] + 4 * y[0] - 2 * y[1] - y[2] <= 2)
    return x, y


@register(
    "macmpec-bilin",
    source=f"{_MACMPEC} bilin (max 18.4); Hansen, Jaumard & Savard (1992), SIAM J. Sci. Stat. Comput. "
           "13:1194-1217, see Luo, Pang & Ralph (1996), MPEC, p. 357. MacMPEC publishes the value only; the "
           "solution point x = (0.5, 0.8), y = (0, 0.2, 0.8) was located by the brute-force check",
    optimum=18.4, solution={"x": [0.5, 0.8], "y": [0.0, 0.2, 0.8]}, lower_optimum=1.8,
    tags=("linear-linear", "max-upper", "textbook"))
def macmpec_bilin() -> BilevelProblem:
    """Hansen-Jaumard-Savard LP: maximising leader, coupling constraint x1 + 2x2 - y3 <= 1.3."""
    p = BilevelProblem()
    x, y = _savard_lower(p)
    p.maximize_upper(8 * x[0] + 4 * x[1] - 4 * y[0] + 40 * y[1] + 4 * y[2])
    return p


@register(
    "basblib-s_1989_01",
    source="BASBLib s_1989_01 (Paulavičius et al.; F* = -14.6 at x = (0, 0.65), y = (0, 0.3, 0)); Savard (1989), "
           "PhD thesis, École Polytechnique de Montréal. Same constraints and follower as macmpec-bilin; the "
           "leader's objective differs in the sign of the y3 term",
    optimum=-14.6, solution={"x": [0.0, 0.65], "y": [0.0, 0.3, 0.0]}, lower_optimum=0.3,
    tags=("linear-linear", "textbook"))
def basblib_s198901() -> BilevelProblem:
    """Savard's LP: minimise -8x1 - 4x2 + 4y1 - 40y2 + 4y3 with the coupling constraint x1 + 2x2 - y3 <= 1.3."""
    p = BilevelProblem()
    x, y = _savard_lower(p)
    p.minimize_upper(-8 * x[0] - 4 * x[1] + 4 * y[0] - 40 * y[1] + 4 * y[2])
    return p
