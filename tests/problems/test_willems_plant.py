"""Willems instances on a plant that is not the batch reactor (the CTMS aircraft pitch model, docs/own_plant.md):
plant and data inputs, the clean learner against the Riccati gain, attacks re-evaluated in numpy; and the batch
reactor's default instance unchanged."""

from __future__ import annotations

import dataclasses
import threading

import control
import numpy as np
import pytest
import scipy.linalg

from bilevel.attacks.willems import destabilize_attack, hypergradient_attack
from bilevel.ddc.data import batch_reactor_data, white_noise_trajectory
from bilevel.ddc.depersis_tesi import lqr_controller
from bilevel.errors import InvalidData, ModelError, NotPersistentlyExciting
from bilevel.problems import registry
from bilevel.problems.willems import build_attack
from bilevel.problems.willems_instance import WillemsSetting
from bilevel.solvers.engine.prepared import prepare
from bilevel.solvers.engine.implicit import Hypergradient

PITCH = control.ss([[-0.313, 56.7, 0.0], [-0.0139, -0.426, 0.0], [0.0, 56.7, 0.0]], [[0.232], [0.0203], [0.0]],
                   np.eye(3), np.zeros((3, 1)))
"""Control Tutorials for MATLAB and Simulink, 'Aircraft Pitch: System Modeling', eqs. (3)-(5): (alpha, q, theta)."""
AIRCRAFT = control.c2d(PITCH, 0.5)


def _riccati_gain(a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
    """u = K x minimizing sum x'x + r u'u (r -> 0: the appendix SDP without input cost), from scipy's DARE."""
    p = scipy.linalg.solve_discrete_are(a, b, np.eye(a.shape[0]), r * np.eye(b.shape[1]))
    return -np.linalg.solve(r * np.eye(b.shape[1]) + b.T @ p @ b, b.T @ p @ a)


def _poisoned_gain(x: np.ndarray, u: np.ndarray, du: np.ndarray) -> np.ndarray:
    """The min-norm learner's gain on inputs u + du (design lqr), computed here: the unregularized SDP's Q (Clarabel)
    projected onto the row space of D = [X0; X1], which input poisoning leaves unchanged, K = (U0 + Du) Q S^-1."""
    d = np.vstack([x[:, :-1], x[:, 1:]])
    q = lqr_controller(x, u, input_cost=False).q
    q = np.linalg.pinv(d) @ (d @ q)
    s = x[:, :-1] @ q
    return np.linalg.solve((s + s.T) / 2, ((u + du) @ q).T).T


def _radius(m: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(m))))


def test_default_instance_is_the_batch_reactors_bit_for_bit() -> None:
    """Seed 0, T = 15: the data as drawn before plants were parameters (the inputs bit for bit, values recorded then),
    the learner's clean gain as the oracle computed it then, and the same declaration keys."""
    attack = build_attack(horizon=15, seed=0)
    x, u = batch_reactor_data(15, np.random.default_rng(0))
    assert np.array_equal(attack.x, x) and np.array_equal(attack.u, u)
    np.testing.assert_allclose(attack.x[:, -1], [3.627522499698449, -1.5839176716286696, -1.064615410431899,
                                                 -1.4721796260494997], rtol=1e-13)  # BLAS kernels differ in ulps
    assert attack.u[:, -1].tolist() == [-1.2459109472530652, 0.2201951234700494]
    gain = _clean_gain(attack)
    before = np.array([[0.9745372322784855, -1.4796511618515098, 0.1662755074405122, -1.8444154166587794],
                       [4.729097597261352, 0.02306510899942071, 3.452333879413107, -1.9186993945818966]])
    np.testing.assert_allclose(gain, before, rtol=1e-6, atol=1e-7)
    assert WillemsSetting() == WillemsSetting(horizon=15) and WillemsSetting().horizon == 15
    assert dict(attack.declaration)["plant"] is None and dict(attack.declaration)["data"] is None


def _clean_gain(attack) -> np.ndarray:
    """The learner's gain on the clean data (the engine's oracle at zero poisoning)."""
    x = np.zeros(attack.upper.numel())
    return attack.loop(x, attack.oracle().evaluate(x).lower.y)[0]


def test_registry_lists_every_setting_parameter() -> None:
    defaults = registry.spec("willems-eigen").defaults
    assert {f.name for f in dataclasses.fields(WillemsSetting)} - set(defaults) == {"objective"}
    assert defaults["horizon"] == 15 and defaults["selection"] == "min-norm" and defaults["qx"] is None
    problem = registry.get("willems-eigen", plant=AIRCRAFT, horizon=20, delta_u=0.3)
    shapes = {v.name: v.shape for v in problem.upper_variables + problem.lower_variables}
    assert shapes["Du"] == (1, 20) and shapes["Q"] == (20, 3)


def test_plant_forms_give_one_hashable_setting() -> None:
    """A StateSpace and its (A, B) arrays make equal settings (plant stored as tuples), and data given equal to the
    drawn ones make the same data and identified model."""
    by_ss = WillemsSetting(plant=AIRCRAFT, horizon=20)
    by_arrays = WillemsSetting(plant=(AIRCRAFT.A, AIRCRAFT.B.ravel()), horizon=20)
    assert by_ss == by_arrays and hash(by_ss) == hash(by_arrays)
    assert dataclasses.replace(by_ss, delta_u=0.2).plant == by_ss.plant
    drawn = build_attack(by_ss)
    given = build_attack(WillemsSetting(plant=AIRCRAFT, data=(drawn.x, drawn.u)))
    assert given.setting.horizon == 20 and hash(given.setting) is not None
    assert np.array_equal(given.x, drawn.x) and np.array_equal(given.a_id, drawn.a_id)
    np.testing.assert_allclose(drawn.a_id, AIRCRAFT.A, atol=1e-9)
    np.testing.assert_allclose(drawn.b_id, AIRCRAFT.B, atol=1e-9)
    scaled = build_attack(WillemsSetting(plant=AIRCRAFT, horizon=20, input_std=2.0, x0=(1.0, 0.0, 0.0)))
    np.testing.assert_array_equal(scaled.u, 2.0 * drawn.u)
    assert scaled.x[:, 0].tolist() == [1.0, 0.0, 0.0]


def test_engine_oracle_keys_on_shape_and_binds_each_attacks_data() -> None:
    """Attacks of one shape (learner, criterion, sizes) share the engine's oracle whatever the budget, the plant or the
    data; each use is bound to the calling attack's data: interleaved, every attack's learner solution equals the one
    of its own constant-data problem (an independent preparation), and other data give another solution."""
    first = build_attack(plant=AIRCRAFT, horizon=20, delta_u=0.1)
    same = build_attack(plant=(AIRCRAFT.A, AIRCRAFT.B), horizon=20, delta_u=0.3)
    slower = build_attack(plant=(0.9 * AIRCRAFT.A, AIRCRAFT.B), horizon=20)
    other = build_attack(plant=AIRCRAFT, horizon=20, seed=1)
    given = build_attack(plant=AIRCRAFT, data=(other.x, other.u))
    assert len({id(a.oracle()) for a in (first, same, slower, given)}) == 1
    zero = np.zeros(first.budget().size)
    own = {id(a): Hypergradient(prepare(a.problem)).evaluate(zero).lower.y for a in (first, slower, given)}
    for attack in (first, slower, given, first, same):
        y = attack.oracle().evaluate(zero).lower.y
        reference = own[id(first)] if attack is same else own[id(attack)]
        np.testing.assert_allclose(y, reference, rtol=0, atol=1e-9 * np.abs(reference).max())
    assert np.abs(own[id(first)] - own[id(slower)]).max() > 1e-3 * np.abs(own[id(first)]).max()


def test_attacks_in_threads_of_one_process_each_keep_their_own_shared_problem() -> None:
    """Attacks of one shape run in threads (a Dask worker with several threads) each bind their data to their own
    thread's shared problem: every thread's attack equals the same attack run alone, twice over."""
    attacks = [build_attack(objective="destabilize", horizon=15, seed=s, delta_u=0.3) for s in range(3)]
    alone = [destabilize_attack(a).x["Du"] for a in attacks]
    got: dict[int, list[np.ndarray]] = {}

    def run(i: int) -> None:
        got[i] = [destabilize_attack(attacks[i]).x["Du"] for _ in range(2)]

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(attacks))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i, du in enumerate(alone):
        for again in got[i]:
            np.testing.assert_array_equal(again, du)


@pytest.mark.parametrize(("design", "r"), [("lqr", 1e-12), ("lqr-r", 1.0)])
def test_clean_learner_gives_the_riccati_gain(design: str, r: float) -> None:
    """Noise-free data (T = 20): the instance's learner (regularized SDP, min-norm Q, KKT-polished) and bilevel.ddc's
    give the LQR gain of the true plant (cheap control for 'lqr', R = I for 'lqr-r'): same within 1e-4 relative
    (measured 5e-6 and 2e-5 for the instance, Clarabel's accuracy)."""
    attack = build_attack(plant=AIRCRAFT, horizon=20, design=design)
    expected = _riccati_gain(AIRCRAFT.A, AIRCRAFT.B, r)
    gain = _clean_gain(attack)
    reference = lqr_controller(attack.x, attack.u, input_cost=design == "lqr-r").k
    for k in (gain, reference):
        assert np.max(np.abs(k - expected)) <= 1e-4 * np.max(np.abs(expected))


def test_attacks_move_the_loop_as_numpy_says() -> None:
    """delta_u = 0.3, T = 20: the destabilizing attack's poisoning, handed to the learner computed here, gives its
    reported gain, spectral radius (true plant, > 1 from 0.949 clean) and identified radius; the eigenvalue attack
    stops at an unstable identified loop whose log det(Acl Acl') is what it reports."""
    radius = destabilize_attack(build_attack(objective="destabilize", plant=AIRCRAFT, horizon=20, delta_u=0.3))
    attack = build_attack(objective="eigen", plant=AIRCRAFT, horizon=20, delta_u=0.3)
    clean = _poisoned_gain(attack.x, attack.u, np.zeros_like(attack.u))
    assert _radius(AIRCRAFT.A + AIRCRAFT.B @ clean) == pytest.approx(0.9491, abs=1e-4)
    du = radius.x["Du"]
    assert np.max(np.abs(du)) <= 0.3 + 1e-12
    gain = _poisoned_gain(attack.x, attack.u, du)
    np.testing.assert_allclose(radius.stats["gain"], gain, rtol=1e-4, atol=1e-4 * np.abs(gain).max())
    rho = _radius(AIRCRAFT.A + AIRCRAFT.B @ gain)
    assert rho > 1.2 and radius.stats["spectral_radius"] == pytest.approx(rho, rel=1e-4)
    assert radius.stats["identified_radius"] == pytest.approx(_radius(attack.a_id + attack.b_id @ gain), rel=1e-4)

    eigen = hypergradient_attack(attack, seed=0)
    gain = _poisoned_gain(attack.x, attack.u, eigen.x["Du"])
    acl = attack.a_id + attack.b_id @ gain
    assert eigen.upper_objective == pytest.approx(2 * np.log(abs(np.linalg.det(acl))), abs=1e-4)
    assert _radius(acl) > 1.0 and eigen.stats["spectral_radius"] == pytest.approx(
        _radius(AIRCRAFT.A + AIRCRAFT.B @ gain), rel=1e-4)


@pytest.mark.parametrize(("plant", "match"), [
    (PITCH, "continuous-time StateSpace; discretize it first, e.g. control.c2d"),
    (control.ss(AIRCRAFT.A, AIRCRAFT.B, np.eye(3), np.ones((3, 1)), 0.5), "needs C = I .* and D = 0"),
    (control.ss(AIRCRAFT.A, AIRCRAFT.B, [[1.0, 0.0, 0.0]], 0.0, 0.5), "got C of shape \\(1, 3\\)"),
    (control.tf([1.0], [1.0, -0.5], 0.5), "StateSpace or an \\(A, B\\) pair, got a TransferFunction"),
    ((np.eye(3), np.ones((2, 1))), "must be n x n and n x m"),
    ((np.eye(3)[:2], np.ones((2, 1))), "must be n x n and n x m"),
    ((np.eye(3), [[np.nan], [0.0], [0.0]]), "NaN or inf"),
    ("pitch", "cannot read \\(A, B\\)"),
])
def test_bad_plants_name_the_fix(plant: object, match: str) -> None:
    with pytest.raises(InvalidData, match=match):
        WillemsSetting(plant=plant)


def test_bad_data_name_the_fix() -> None:
    drawn = build_attack(plant=AIRCRAFT, horizon=20)
    x, u = drawn.x, drawn.u
    with pytest.raises(InvalidData, match="the default plant \\(the batch reactor; pass plant=\\) has n = 4 states"):
        WillemsSetting(data=(x, u))
    with pytest.raises(InvalidData, match="X holds one more sample"):
        WillemsSetting(plant=AIRCRAFT, data=(x[:, :-1], u))
    with pytest.raises(InvalidData, match="NaN/inf"):
        WillemsSetting(plant=AIRCRAFT, data=(x, np.where(np.arange(20) == 3, np.nan, u)))
    with pytest.raises(ModelError, match="horizon=15 but the data have T = 20 samples; pass horizon=None"):
        WillemsSetting(plant=AIRCRAFT, data=(x, u), horizon=15)
    with pytest.raises(ModelError, match="x0 and input_std describe drawn data"):
        WillemsSetting(plant=AIRCRAFT, data=(x, u), input_std=2.0)
    with pytest.raises(InvalidData, match="the pair \\(X, U\\)"):
        WillemsSetting(plant=AIRCRAFT, data=x)
    short = "T >= n \\+ m = 4 samples.*T = 3.*Fix: a longer horizon.*or a richer input"
    with pytest.raises(NotPersistentlyExciting, match=short):
        build_attack(WillemsSetting(plant=AIRCRAFT, data=(x[:, :4], u[:, :3])))
    uncontrollable = (np.diag([0.5, 0.6, 0.7]), [[1.0], [1.0], [0.0]])  # x_3 never moves from x_0 = 0
    with pytest.raises(NotPersistentlyExciting, match="rank \\[U0; X0\\] = 3 but n \\+ m = 4.*uncontrollable"):
        build_attack(plant=uncontrollable, horizon=50)


@pytest.mark.parametrize(("params", "error", "match"), [
    ({"input_std": 0.0}, ModelError, "input_std=0.0 is invalid: it must be a finite number > 0"),
    ({"x0": (1.0, 2.0)}, InvalidData, "x0 must be the plant's 3 initial states"),
    ({"x0": "zero"}, InvalidData, "x0='zero': give n numbers, None"),
    ({"qx": [[1.0, 0.0], [0.0]]}, ModelError, "qx must be a square matrix"),
])
def test_bad_drawing_parameters_are_refused(params: dict, error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        WillemsSetting(plant=AIRCRAFT, **params)


def test_white_noise_trajectory_refuses_an_unknown_initial_state_word() -> None:
    with pytest.raises(InvalidData, match="x0='zero': give the initial state as n numbers, None"):
        white_noise_trajectory(AIRCRAFT.A, AIRCRAFT.B, 5, np.random.default_rng(0), x0="zero")
