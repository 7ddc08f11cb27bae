"""Certified robustness against data poisoning: proofs that no poisoning within a budget destabilizes the true loop
(or bounds on the attacker's objective), with independently re-checked evidence, and the bracket [delta_lb,
delta_ub] of the smallest destabilizing budget next to the project's attacks (docs/certify.md)."""

from . import deepc, depersis_tesi, generic, identification, vrft  # noqa: F401  (their targets and mechanisms register)
from .chain import attack_bound, certified_margin, certify
from .soundness import Soundness, sample_soundness, sphere_poisoning
from .target import MECHANISMS, Target, as_target, mechanisms_of, register_mechanism, register_target
from .verdict import Check, Evidence, Margin, Proof, RobustnessCertificate, proof_of

__all__ = [
    "MECHANISMS", "Check", "Evidence", "Margin", "Proof", "RobustnessCertificate", "Soundness", "Target",
    "as_target", "attack_bound", "certified_margin", "certify", "mechanisms_of", "proof_of", "register_mechanism",
    "register_target", "sample_soundness", "sphere_poisoning",
]
