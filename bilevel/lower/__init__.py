"""Lower-level kinds (least squares, LP, QP, convex NLP, SDP): each solves itself and states its KKT system."""

from .base import ExpressionLower, KKTSystem, LowerLevel, LowerSolution
from .classify import build_lower
from .least_squares import LeastSquaresLower
from .nlp import ConvexNLPLower
from .quadratic import LinearLower, QPData, QuadraticLower
from .sdp import SemidefiniteLower

__all__ = ["ConvexNLPLower", "ExpressionLower", "KKTSystem", "LeastSquaresLower", "LinearLower", "LowerLevel",
           "LowerSolution", "QPData", "QuadraticLower", "SemidefiniteLower", "build_lower"]
