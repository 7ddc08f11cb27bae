"""What a robustness certificate says: the proof's strength, the evidence behind it with its independent re-check,
and the bracket [delta_lb, delta_ub] of the smallest destabilizing budget.

A certificate is `proven` only when a piece of its evidence claims a proof and that evidence's independent re-check
passed; evidence that claims a proof but fails its re-check makes the certificate `unknown`, never `proven`.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from enum import Enum
from typing import Any

from ..errors import ModelError


class Proof(str, Enum):
    """How strong a certificate is."""

    PROVEN = "proven"      # no poisoning within delta reaches the attacker's goal (evidence re-checked)
    BOUNDED = "bounded"    # a proven upper bound on the attacker's objective, with a gap to the best attack found
    REFUTED = "refuted"    # a poisoning within delta reaches the goal (re-checked by a numpy re-fit)
    UNKNOWN = "unknown"    # no mechanism proved or refuted, or its evidence failed its re-check


@dataclass(frozen=True)
class Check:
    """The independent re-check of a piece of evidence: its verdict, what was checked, and the numbers it found
    (e.g. the smallest eigenvalue numpy found and the margin above rounding it had to exceed)."""

    passed: bool
    detail: str
    numbers: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Evidence:
    """What one mechanism established at a budget: its claim (`proof`, in words `claim`), its numbers (a bound, a
    margin), its independent re-check, and its time (seconds)."""

    mechanism: str
    proof: Proof
    claim: str
    numbers: dict[str, float]
    check: Check
    seconds: float

    @property
    def holds(self) -> bool:
        """Whether the claim stands: it claims more than `unknown` and its re-check passed."""
        return self.proof is not Proof.UNKNOWN and self.check.passed


def _floats(d: dict[str, Any]) -> dict[str, float]:
    return {str(k): float(v) for k, v in d.items()}


@dataclass(frozen=True)
class RobustnessCertificate:
    """The verdict on one target at one budget delta: the proof (from the evidence: `proof_of`), the claim in words,
    a proven upper bound on the attacker's objective where a mechanism gives one (None otherwise), every piece of
    evidence tried (cheapest first) and the total time."""

    target: str
    delta: float | None
    proof: Proof
    claim: str
    evidence: tuple[Evidence, ...]
    seconds: float
    bound: float | None = None

    def __post_init__(self) -> None:
        if self.proof is not proof_of(self.evidence):
            raise ModelError(f"a certificate's proof must follow from its evidence: {self.proof.value} given, the "
                              f"evidence supports {proof_of(self.evidence).value}")

    @property
    def proven(self) -> bool:
        return self.proof is Proof.PROVEN

    def to_json(self) -> str:
        d = asdict(self)
        d["proof"] = self.proof.value
        for e in d["evidence"]:
            e["proof"] = Proof(e["proof"]).value
        return json.dumps(d, default=_json_number)

    @classmethod
    def from_json(cls, text: str) -> "RobustnessCertificate":
        d = json.loads(text)
        evidence = tuple(Evidence(e["mechanism"], Proof(e["proof"]), e["claim"], _floats(e["numbers"]),
                                  Check(bool(e["check"]["passed"]), e["check"]["detail"],
                                        _floats(e["check"]["numbers"])), float(e["seconds"]))
                         for e in d["evidence"])
        return cls(d["target"], None if d["delta"] is None else float(d["delta"]), Proof(d["proof"]), d["claim"],
                   evidence, float(d["seconds"]), None if d["bound"] is None else float(d["bound"]))


def _json_number(value: Any) -> Any:
    """numpy scalars as Python numbers (json's fallback)."""
    if hasattr(value, "item"):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


RANK = {Proof.REFUTED: 3, Proof.PROVEN: 2, Proof.BOUNDED: 1, Proof.UNKNOWN: 0}
"""Which standing claim decides a certificate: a re-checked refutation beats a proof (they cannot both hold: one of
them has a bug, and the certificate must not claim safety), a proof beats a bound."""


def proof_of(evidence: tuple[Evidence, ...] | list[Evidence]) -> Proof:
    """The strongest claim among the evidence that holds (re-checked), `unknown` if none does."""
    standing = [e.proof for e in evidence if e.holds]
    return max(standing, key=RANK.__getitem__, default=Proof.UNKNOWN)


@dataclass(frozen=True)
class Margin:
    """The bracket of the smallest destabilizing budget: delta_lb, the largest budget proven safe (0 if none);
    delta_ub, the smallest budget at which the attack reached its goal (inf if none on its path); ratio =
    delta_ub / delta_lb; the certificate at delta_lb, the attack's runs (budget, outcome) and the time of each side."""

    target: str
    delta_lb: float
    delta_ub: float
    certificate: RobustnessCertificate | None
    attack_runs: tuple[tuple[float, float], ...]
    seconds_lb: float
    seconds_ub: float

    @property
    def ratio(self) -> float:
        return self.delta_ub / self.delta_lb if self.delta_lb > 0 else math.inf

    @property
    def consistent(self) -> bool:
        """0 <= delta_lb <= delta_ub (a proof above a real attack would be a bug)."""
        return 0.0 <= self.delta_lb <= self.delta_ub

    def to_json(self) -> str:
        return json.dumps({"target": self.target, "delta_lb": self.delta_lb, "delta_ub": self.delta_ub,
                           "ratio": self.ratio, "attack_runs": [list(r) for r in self.attack_runs],
                           "seconds_lb": self.seconds_lb, "seconds_ub": self.seconds_ub,
                           "certificate": None if self.certificate is None else json.loads(self.certificate.to_json())},
                          default=_json_number)
