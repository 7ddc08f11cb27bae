"""The certificate framework (bilevel.robust): verdicts follow from re-checked evidence, the chain stops at the
first proof, the registries refuse bad names, the generic target's global bound on a literature optimum, and the
sampling check on a VRFT target."""

from __future__ import annotations

import numpy as np
import pytest

import bilevel as bl
from bilevel.errors import ModelError, UnknownName
from bilevel.problems import registry
from bilevel.problems.vrft_instance import attack_instance
from bilevel.robust import (Check, Evidence, Margin, Proof, RobustnessCertificate, Target, as_target, certify,
                            proof_of, register_mechanism, sample_soundness, sphere_poisoning)
from bilevel.robust.target import MECHANISMS


def _evidence(proof: Proof, passed: bool, name: str = "m") -> Evidence:
    return Evidence(name, proof, f"{name} says {proof.value}", {"bound": 1.5}, Check(passed, "re-checked",
                                                                                     {"min_eig": 0.25}), 0.01)


def test_a_failed_check_is_unknown_never_proven() -> None:
    assert proof_of([_evidence(Proof.PROVEN, True)]) is Proof.PROVEN
    assert proof_of([_evidence(Proof.PROVEN, False)]) is Proof.UNKNOWN
    assert proof_of([_evidence(Proof.BOUNDED, True), _evidence(Proof.PROVEN, False)]) is Proof.BOUNDED
    assert proof_of([_evidence(Proof.PROVEN, True), _evidence(Proof.REFUTED, True)]) is Proof.REFUTED
    assert proof_of([]) is Proof.UNKNOWN
    with pytest.raises(ModelError, match="must follow from its evidence"):
        RobustnessCertificate("t", 0.1, Proof.PROVEN, "claim", (_evidence(Proof.PROVEN, False),), 0.1)


def test_certificate_json_round_trip() -> None:
    cert = RobustnessCertificate("t", 0.1, Proof.PROVEN, "claim", (_evidence(Proof.PROVEN, True),), 0.1, 1.5)
    back = RobustnessCertificate.from_json(cert.to_json())
    assert back == cert
    margin = Margin("t", 0.02, 0.05, cert, ((0.05, 1.01),), 1.0, 2.0)
    assert margin.ratio == pytest.approx(2.5) and margin.consistent
    assert '"ratio": 2.5' in margin.to_json()


def test_the_chain_stops_at_the_first_rechecked_proof() -> None:
    calls: list[str] = []

    def mech(name: str, proof: Proof, passed: bool):
        def fn(target: Target, delta: float, options: dict) -> Evidence:
            calls.append(name)
            return _evidence(proof, passed, name)
        return fn

    register_mechanism("test-family", mech("cheap-unchecked", Proof.PROVEN, False), "cheap", cost=0)
    register_mechanism("test-family", mech("middle", Proof.PROVEN, True), "middle", cost=1)
    register_mechanism("test-family", mech("dear", Proof.PROVEN, True), "dear", cost=2)
    try:
        target = Target("toy", "test-family", None)
        cert = certify(target, 0.1)
        assert cert.proof is Proof.PROVEN and calls == ["cheap-unchecked", "middle"]
        assert cert.claim == "middle says proven" and cert.bound == 1.5
        assert certify(target, 0.1, mechanisms=["cheap"]).proof is Proof.UNKNOWN
        assert "failed its independent re-check" in certify(target, 0.1, mechanisms=["cheap"]).claim
        with pytest.raises(UnknownName, match="no mechanism 'nope'"):
            certify(target, 0.1, mechanisms=["nope"])
        with pytest.raises(ModelError, match="already registered"):
            register_mechanism("test-family", mech("x", Proof.PROVEN, True), "dear")
        with pytest.raises(ModelError, match="positive budget"):
            certify(target, -1.0)
    finally:
        del MECHANISMS["test-family"]


def test_as_target_refuses_what_it_cannot_certify() -> None:
    with pytest.raises(ModelError, match="cannot certify a str"):
        as_target("vrft")
    assert as_target(registry.get("macmpec-bilin")).family == "generic"


def test_generic_global_bound_is_rechecked_by_a_second_algorithm() -> None:
    """MacMPEC bilin (Hansen, Jaumard & Savard 1992): max 18.4. HiGHS's MILP and the branch-and-bound on the pairs
    both bound it, and the bound is the literature's optimum."""
    cert = certify(registry.get("macmpec-bilin"))
    assert cert.proof is Proof.BOUNDED, cert.claim
    assert cert.bound == pytest.approx(18.4, abs=1e-5)
    ev = cert.evidence[0]
    assert ev.check.passed and ev.check.numbers["second_bound"] == pytest.approx(18.4, abs=1e-5)


def test_sphere_samples_sit_on_the_budget_sphere_and_a_small_budget_is_sound() -> None:
    target = as_target(attack_instance("destabilize", "B", 0.0, 0.0, seed=0, N=64))
    rng = np.random.default_rng(1)
    p = sphere_poisoning(target, 0.01, rng)
    assert np.linalg.norm(p["y"]) == pytest.approx(0.01 * np.linalg.norm(target.signals["y"]), rel=1e-12)
    clean = target.true_radius({})
    assert clean < 1.0
    report = sample_soundness(target, 1e-4, samples=50, attacks=False)
    assert report.sound and report.samples == 50 and abs(report.worst_radius - clean) < 1e-2


def test_package_exports() -> None:
    assert bl.certify is certify and bl.Proof is Proof
    assert bl.certify_point.__module__ == "bilevel.certificate"
