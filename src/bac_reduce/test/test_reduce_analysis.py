"""Significance and similarity on functions whose important parameters and groups are known (no simulator)."""

from __future__ import annotations

import numpy as np
import pytest

from bac_common.errors import OutOfBoundsError
from bac_common.paramspace import CalibrationDefinition, MetaParameter, RawParameter
from bac_reduce.analysis import (
    Group,
    ReductionError,
    check_ties,
    reduced_definition,
    sensitivity_curves,
    significant,
    similarity_groups,
    tied_sweep,
)
from bac_reduce.objectives import SyntheticObjective, SyntheticTerm

BOUNDS8 = np.array([[0.0, 1000.0]] * 8)


def synthetic_curves(obj: SyntheticObjective, points: int = 51):
    names = [t.name for t in obj.terms]
    return sensitivity_curves(obj.raw_j, obj.optimum, np.array([[obj.lower, obj.upper]] * len(names)), names, points)


def test_worst_losses_are_the_analytic_ones() -> None:
    obj = SyntheticObjective()
    c = synthetic_curves(obj)
    assert c.j_bar == pytest.approx(1.0)
    # from the optimum, the worst value of w (r - o)^2 is at the far end of the range: w max(o, 1 - o)^2
    expected = [t.weight * max(t.optimum, 1 - t.optimum) ** 2 for t in obj.terms]
    np.testing.assert_allclose(c.loss, expected, rtol=1e-9)
    np.testing.assert_allclose(c.best_value, [1000 * t.optimum for t in obj.terms], atol=1e-9)
    assert c.values.shape == (8, 51) and c.s.shape == (8, 51)


def test_significance_keeps_the_parameters_above_t() -> None:
    c = synthetic_curves(SyntheticObjective())
    assert significant(c, 0.05) == ("q1", "q2", "q3", "q4", "q5", "q6")
    assert significant(c, 0.0) == tuple(f"q{i}" for i in range(1, 9))  # every parameter moves J a little
    assert significant(c, 0.15) == ("q1", "q2", "q4", "q5")  # 19.2, 16, 25.6, 20 % (q3 12.8, q6 15.0 exactly)
    with pytest.raises(ReductionError, match="threshold"):
        significant(c, -0.1)


def test_similarity_finds_the_known_groups() -> None:
    obj = SyntheticObjective()
    c = synthetic_curves(obj)
    kept = significant(c)
    groups = similarity_groups(c, kept, epsilon=0.05, flat_tol=0.0)  # the paper's rule: argmins within ε
    assert [g.members for g in groups] == [("q1", "q2", "q3"), ("q4",), ("q5", "q6")]
    # near-optimal within 0.5 % of J: q4 [0.1, 0.3], q5 [0, 0.14], q6 [0, 0.18] overlap, so the three are grouped
    # first; tied at a common value they lose 0.6 % > tie_tol 0.5 %, and q4, farthest from it, leaves the group
    loose = similarity_groups(c, kept, epsilon=0.05, flat_tol=0.005)
    assert [g.members for g in loose] == [("q1", "q2", "q3"), ("q4", "q5", "q6")]
    checked = check_ties(obj.raw_j, c, loose, tie_tol=0.005)
    assert [g.members for g in checked] == [("q1", "q2", "q3"), ("q4",), ("q5", "q6")]
    assert check_ties(obj.raw_j, c, loose, tie_tol=0.01)[1].members == ("q4", "q5", "q6")
    assert [g.value for g in groups] == pytest.approx([0.8, 0.2, 0.0])
    checked = check_ties(obj.raw_j, c, groups)
    assert [g.members for g in checked] == [g.members for g in groups]
    # the optimum is shared: tying the members costs nothing (the group value is the tied sweep's argmin)
    assert [g.tie_loss for g in checked] == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)
    assert [g.value for g in checked] == pytest.approx([0.8, 0.2, 0.0])


def test_similarity_does_not_depend_on_the_order_of_the_parameters() -> None:
    obj = SyntheticObjective()
    c = synthetic_curves(obj)
    kept = list(significant(c))
    ref = {g.members for g in similarity_groups(c, kept)}
    rng = np.random.default_rng(3)
    for _ in range(5):
        rng.shuffle(kept)
        assert {g.members for g in similarity_groups(c, kept)} == ref


def chain_objective(optima: list[float]) -> SyntheticObjective:
    terms = tuple(SyntheticTerm(f"a{i}", o, 0.3) for i, o in enumerate(optima))
    return SyntheticObjective(terms=terms, coupling=0.0)


def test_epsilon_groups_are_pairwise_within_epsilon() -> None:
    # optima 0.20, 0.24, 0.28, 0.32: a chain of neighbours 0.04 apart; with ε = 0.05 no group may span more than ε
    obj = chain_objective([0.20, 0.24, 0.28, 0.32, 0.90])
    c = sensitivity_curves(obj.raw_j, obj.optimum, np.array([[0.0, 1000.0]] * 5), [t.name for t in obj.terms], 101)
    groups = similarity_groups(c, c.names, epsilon=0.05, flat_tol=0.0)
    assert [g.members for g in groups] == [("a0", "a1"), ("a2", "a3"), ("a4",)]
    for g in groups:
        opts = [obj.terms[int(m[1:])].optimum for m in g.members]
        assert max(opts) - min(opts) <= 0.05 + 1e-12
    # a larger ε joins the chain, ε = 0 separates everything
    assert [g.members for g in similarity_groups(c, c.names, epsilon=0.13, flat_tol=0.0)] == [
        ("a0", "a1", "a2", "a3"),
        ("a4",),
    ]
    assert len(similarity_groups(c, c.names, epsilon=0.0, flat_tol=0.0)) == 5


def test_a_flat_bottomed_curve_joins_a_group_inside_its_flat_region() -> None:
    # b is optimal anywhere in [0, 0.5] (a one-sided penalty); a's optimum 0.3 lies in that region
    def surrogate(X: np.ndarray) -> np.ndarray:
        r = X / 1000.0
        return 1.0 + 0.5 * (r[:, 0] - 0.3) ** 2 + 2.0 * np.maximum(r[:, 1] - 0.5, 0.0) ** 2

    c = sensitivity_curves(surrogate, np.array([300.0, 200.0]), np.array([[0.0, 1000.0]] * 2), ["a", "b"], 51)
    iv = c.optimal_intervals(0.005)
    assert iv[1, 0] == pytest.approx(0.0) and 0.5 <= iv[1, 1] < 0.6  # near-optimal within 0.5 % of J: [0, 0.54]
    assert iv[0, 0] < 0.3 < iv[0, 1]
    together = similarity_groups(c, ["a", "b"], epsilon=0.05, flat_tol=0.005)
    assert [g.members for g in together] == [("a", "b")]
    assert together[0].value == pytest.approx(0.3, abs=0.11)
    # exactly equal values are equal optima even with flat_tol = 0: the interval is the whole flat bottom (the
    # grid argmin alone, 0, would be an arbitrary pick that separates b from a)
    assert c.optimal_intervals(0.0)[1] == pytest.approx([0.0, 0.5])
    assert [g.members for g in similarity_groups(c, ["a", "b"], epsilon=0.05, flat_tol=0.0)] == [("a", "b")]
    # a curve that is not flat at all keeps a point interval
    assert c.optimal_intervals(0.0)[0] == pytest.approx([0.3, 0.3])
    # tied at a's optimum both are optimal: the check keeps the group
    checked = check_ties(surrogate, c, together)
    assert checked[0].members == ("a", "b") and checked[0].tie_loss == pytest.approx(0.0, abs=1e-3)


def test_tie_check_splits_a_group_whose_members_cannot_move_together() -> None:
    # one-at-a-time, a and b look alike (optima 0.48 and 0.52 within ε = 0.05); tied they cannot both be
    # optimal and J is steep: tying costs 100 (0.02^2) · 2 = 8 % > 1 %; c shares a's optimum exactly
    def surrogate(X: np.ndarray) -> np.ndarray:
        r = X / 1000.0
        return 1.0 + 100 * (r[:, 0] - 0.48) ** 2 + 100 * (r[:, 1] - 0.52) ** 2 + 100 * (r[:, 2] - 0.48) ** 2

    c = sensitivity_curves(
        surrogate, np.array([480.0, 520.0, 480.0]), np.array([[0.0, 1000.0]] * 3), ["a", "b", "c"], 101
    )
    groups = similarity_groups(c, ["a", "b", "c"], epsilon=0.05, flat_tol=0.0)
    assert [g.members for g in groups] == [("a", "b", "c")]
    _u, j = tied_sweep(surrogate, c, ["a", "b", "c"])
    assert (j.min() - c.j_bar) / c.j_bar > 0.01
    checked = check_ties(surrogate, c, groups, tie_tol=0.01)
    assert sorted(g.members for g in checked) == [("a", "c"), ("b",)]
    ac = next(g for g in checked if g.members == ("a", "c"))
    assert ac.tie_loss == pytest.approx(0.0, abs=1e-9) and ac.value == pytest.approx(0.48)


def test_optimal_interval_is_the_contiguous_stretch_around_the_argmin() -> None:
    # two dips: the global one at 0.2 and a slightly worse one at 0.8; the interval covers only the first
    def surrogate(X: np.ndarray) -> np.ndarray:
        r = X[:, 0] / 1000.0
        return 1.0 + np.minimum((r - 0.2) ** 2, (r - 0.8) ** 2 + 0.001)

    c = sensitivity_curves(surrogate, np.array([200.0]), np.array([[0.0, 1000.0]]), ["x"], 101)
    a, b = c.optimal_intervals(0.005)[0]
    assert a < 0.2 < b < 0.5  # (r - 0.2)^2 <= 0.005 -> |r - 0.2| <= 0.07
    assert a == pytest.approx(0.13, abs=0.011) and b == pytest.approx(0.27, abs=0.011)
    a0, b0 = c.optimal_intervals(0.0)[0]
    assert a0 == b0 == pytest.approx(0.2)


def test_bad_inputs_are_refused_with_reasons() -> None:
    obj = SyntheticObjective()
    names = [t.name for t in obj.terms]
    with pytest.raises(ReductionError, match="bounds"):
        sensitivity_curves(obj.raw_j, obj.optimum, np.array([[0.0, 0.0]] * 8), names)
    with pytest.raises(ReductionError, match="outside the bounds"):
        sensitivity_curves(obj.raw_j, obj.optimum + 2000, BOUNDS8, names)
    with pytest.raises(ReductionError, match="names"):
        sensitivity_curves(obj.raw_j, obj.optimum, BOUNDS8, names[:3])
    with pytest.raises(ReductionError, match="non-finite"):
        sensitivity_curves(lambda X: np.full(X.shape[0], np.nan), obj.optimum, BOUNDS8, names)
    with pytest.raises(ReductionError, match="positive"):
        sensitivity_curves(lambda X: np.full(X.shape[0], -1.0), obj.optimum, BOUNDS8, names)
    c = synthetic_curves(obj)
    with pytest.raises(ReductionError, match="epsilon"):
        similarity_groups(c, ["q1"], epsilon=2.0)
    with pytest.raises(ReductionError, match="not in the curves"):
        similarity_groups(c, ["nope"])


def controller(n: int = 6) -> CalibrationDefinition:
    params = tuple(RawParameter(f"p{i:02d}", i, 0.0, 1000.0, 500.0, 0.01) for i in range(1, n + 1))
    return CalibrationDefinition("ctl", params)


def test_reduced_definition_drives_members_and_fixes_the_rest() -> None:
    base = controller()
    groups = [
        Group(("p01", "p03"), 0.8, ((0.8, 0.8), (0.8, 0.8))),
        Group(("p02",), 0.1, ((0.1, 0.1),)),
        Group(("p04", "p05"), 0.0, ((0.0, 0.0), (0.0, 0.0))),
    ]
    theta_bar = {f"p{i:02d}": 100.0 * i + 0.004 for i in range(1, 7)}
    red = reduced_definition(base, groups, theta_bar)
    assert red.name == "ctl_reduced"
    assert red.tuned == ("m1", "p02", "m2")
    assert red.meta[0] == MetaParameter("m1", ("p01", "p03"), 0.0, 1000.0, red.meta[0].description)
    assert red.fixed == {"p06": 600.0}  # quantized to the CAN resolution (0.01)
    raw = red.expand({"m1": 750.0, "p02": 12.5, "m2": 3.0})
    assert raw == {"p01": 750.0, "p02": 12.5, "p03": 750.0, "p04": 3.0, "p05": 3.0, "p06": 600.0}
    with pytest.raises(OutOfBoundsError):
        red.expand({"m1": 1200.0, "p02": 12.5, "m2": 3.0})
    # it round-trips through YAML and the ECU bridge's expansion is the same
    back = CalibrationDefinition.from_dict(red.to_dict())
    assert back.expand({"m1": 750.0, "p02": 12.5, "m2": 3.0}) == raw


def test_reduced_definition_refuses_what_cannot_be_written() -> None:
    base = controller()
    g = [Group(("p01",), 0.5, ((0.5, 0.5),))]
    with pytest.raises(ReductionError, match="no fixed value"):
        reduced_definition(base, g, {"p02": 1.0})
    with pytest.raises(ReductionError, match="two groups"):
        reduced_definition(base, [*g, Group(("p01", "p02"), 0.5, ((0.5, 0.5), (0.5, 0.5)))], {})
    with pytest.raises(ReductionError, match="no parameter was kept"):
        reduced_definition(base, [], {})
    already = reduced_definition(base, g, {f"p{i:02d}": 1.0 for i in range(1, 7)})
    with pytest.raises(ReductionError, match="every raw parameter directly"):
        reduced_definition(already, g, {})
