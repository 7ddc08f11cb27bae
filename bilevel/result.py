"""The result of every solve: one status vocabulary, fields that always exist, JSON round trip."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from enum import Enum
from typing import Any

import casadi as ca
import numpy as np

from .certificate import Certificate, GlobalBound
from .errors import InvalidData, renamed
from .files import atomic_open

SHOWN = 12
"""Arrays with more entries than this print as a summary (size, norm, first and last entries)."""

_CERT_FLOATS = ("stationarity", "lower_feasibility", "dual_feasibility", "complementarity", "upper_feasibility",
                "lower_gap", "lower_reference", "tolerance", "y_distance")


class Status(str, Enum):
    """What a solve achieved; `success` is true only for SOLVED."""

    SOLVED = "solved"                          # backend converged and the certificate passed
    INACCURATE = "inaccurate"                  # certificate passed, backend stopped short (e.g. acceptable level)
    CERTIFICATE_FAILED = "certificate_failed"  # backend claimed success, certificate disagrees
    NOT_LOCALLY_OPTIMAL = "not_locally_optimal"  # certificate passed, but a feasible point nearby is better
    MAX_ITERATIONS = "max_iterations"          # iteration/time limit hit, certificate not passed
    INFEASIBLE = "infeasible"                  # backend found the single-level problem infeasible
    ERROR = "error"                            # backend failed without a usable point


@dataclass(frozen=True)
class BilevelResult:
    """A solve's outcome. x, y and multipliers are keyed by declared names; objectives in declared senses.

    history: per-iteration (or per-relaxation-step) records of the method; stats: raw backend output,
    with no stability promise; start_records: one summary per multistart start (option `starts` is their count).
    Whatever the status, upper_objective is F at the reported (x, y), and where the certificate shows that the
    method's y is no lower solution at x, y is the certificate's re-solve (the method's in stats["method_y"]).
    """

    status: Status
    message: str
    method: str
    problem: str
    x: dict[str, np.ndarray]
    y: dict[str, np.ndarray]
    multipliers: dict[str, np.ndarray]
    upper_objective: float | None
    lower_objective: float | None
    certificate: Certificate | None
    wall_time: float
    nit: int
    history: tuple[dict[str, Any], ...] = ()
    start_records: tuple[dict[str, Any], ...] = ()
    stats: dict[str, Any] = field(default_factory=dict)
    _evaluate: Any = field(default=None, repr=False, compare=False)

    @property
    def success(self) -> bool:
        return self.status is Status.SOLVED

    @property
    def starts(self) -> None:
        """Renamed: the per-start records are start_records (`starts` is the option that counts them)."""
        raise AttributeError(renamed("BilevelResult.starts", "start_records (the per-start records; the option starts "
                                     "is their count)"))

    def value(self, expr: Any) -> float | np.ndarray:
        """Evaluate any CasADi expression of the problem's variables at the solution."""
        if self._evaluate is None:
            raise ValueError(f"this result carries no point (status {self.status.value}); nothing to evaluate")
        out = np.asarray(self._evaluate(ca.SX(expr)))
        return out.item() if out.size == 1 else out.squeeze()

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (arrays as nested lists; raw stats reduced to JSON-safe entries)."""
        def clean(v: Any) -> Any:
            if isinstance(v, np.ndarray):
                return clean(v.tolist())
            if isinstance(v, (np.floating, np.integer)):
                v = v.item()
            if isinstance(v, float) and not np.isfinite(v):
                return None  # JSON has no NaN/inf
            if isinstance(v, dict):
                return {str(k): clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [clean(x) for x in v]
            if isinstance(v, Enum):
                return v.value
            return v if isinstance(v, (str, int, float, bool, type(None))) else repr(v)

        d = {k: getattr(self, k) for k in ("status", "message", "method", "problem", "upper_objective",
                                            "lower_objective", "wall_time", "nit", "x", "y", "multipliers",
                                            "history", "start_records", "stats")}
        d["success"] = self.success
        d["certificate"] = None if self.certificate is None else asdict(self.certificate)
        return clean(d)

    def to_json(self, path: str | None = None, indent: int = 2) -> str:
        """Serialize to strict JSON (NaN and inf become null); also write it to `path` when given."""
        text = json.dumps(self.to_dict(), indent=indent, allow_nan=False)
        if path is not None:
            with atomic_open(path) as fh:
                fh.write(text)
        return text

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "BilevelResult":
        """Rebuild a result from to_dict() output (arrays as numpy, null numbers as NaN; no evaluator)."""
        arrays = lambda m: {k: np.asarray(v, dtype=float) for k, v in (m or {}).items()}  # noqa: E731
        num = lambda v: np.nan if v is None else float(v)  # noqa: E731
        cert = d.get("certificate")
        if cert is not None:
            names = {f.name for f in fields(Certificate)}
            cert = {k: v for k, v in cert.items() if k in names}
            bound = cert.get("global_bound")
            cert = Certificate(**{**cert, **{k: num(cert[k]) for k in _CERT_FLOATS if k in cert},
                                  "failed": tuple(cert.get("failed", ())),
                                  "global_bound": None if bound is None else GlobalBound(**{
                                      **bound, **{k: num(bound[k]) for k in ("lower_bound", "upper_bound", "gap")},
                                      "big_m": tuple(bound.get("big_m", ()))}),
                                  "lower_reference_y": [num(v) for v in cert.get("lower_reference_y", [])]})
        return cls(Status(d["status"]), d["message"], d["method"], d["problem"], arrays(d.get("x")),
                   arrays(d.get("y")), arrays(d.get("multipliers")),
                   None if d.get("upper_objective") is None else float(d["upper_objective"]),
                   None if d.get("lower_objective") is None else float(d["lower_objective"]), cert,
                   float(d.get("wall_time") or 0.0), int(d.get("nit") or 0), tuple(d.get("history", ())),
                   tuple(d.get("start_records", d.get("starts", ()))), dict(d.get("stats", {})))

    @classmethod
    def from_json(cls, source: str) -> "BilevelResult":
        """Read a result written by to_json: `source` is a JSON text or the path of a file holding one; a text that
        is not such a result raises InvalidData naming what is wrong."""
        text = source
        if not source.lstrip().startswith("{"):
            with open(source, encoding="utf-8") as fh:
                text = fh.read()
        try:
            d = json.loads(text)
            return cls.from_dict(d)
        except (ValueError, KeyError, TypeError) as exc:  # JSONDecodeError is a ValueError
            raise InvalidData(f"not a result written by BilevelResult.to_json ({type(exc).__name__}: {exc}); pass "
                              "the text or the path of a file that to_json wrote") from exc

    def __repr__(self) -> str:
        def array(a: np.ndarray) -> str:
            if a.size <= SHOWN:
                return np.array2string(a, precision=6)
            size = f"{a.size}" if a.ndim == 1 else "x".join(map(str, a.shape))
            return (f"{size} entries, norm {np.linalg.norm(a):.6g}, "
                    f"{np.array2string(a.ravel(), precision=6, threshold=0, edgeitems=3)}")

        def fmt(v: Any) -> str:
            if isinstance(v, dict):
                return "{" + ", ".join(f"{k}: {array(np.asarray(a))}" for k, a in v.items()) + "}"
            return repr(v)

        keys = [("status", self.status.value), ("success", self.success), ("message", self.message),
                ("upper_objective", self.upper_objective), ("lower_objective", self.lower_objective),
                ("x", self.x), ("y", self.y), ("method", self.method), ("nit", self.nit),
                ("wall_time", round(self.wall_time, 4)), ("certificate", self.certificate)]
        width = max(len(k) for k, _ in keys)
        return "\n".join(f"{k.rjust(width)}: {fmt(v)}" for k, v in keys)
