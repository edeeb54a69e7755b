"""Tests of memlog.evaluate.metrics against cases worked out by hand."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from memlog.errors import EvaluationError
from memlog.evaluation.metrics import (
    auc_pr_trapezoid,
    coverage,
    evaluate_map_only,
    evaluate_paper,
    parse_truth,
    pr_curve,
    precision_at_full_recall,
    recall_at_full_precision,
    recall_at_n,
    truth_from_positions,
)
from memlog.descriptors.search import match
from tests.conftest import shared



# ---------------------------------------------------------------- AUC (paper eq. 2)

@pytest.mark.parametrize(
    ("precision", "recall", "expected"),
    [
        # 1) perfect: (1+1)/2 * (1-0) = 1
        ([1.0, 1.0], [0.0, 1.0], 1.0),
        # 2) (1+.5)/2*(.5-.5) + (.5+2/3)/2*(1-.5) = 0 + (7/6)/2*.5 = 7/24
        ([1.0, 0.5, 2 / 3], [0.5, 0.5, 1.0], 7 / 24),
        # 3) only the last step moves recall: (1/3+1/2)/2 * (2/3-1/3) = (5/6)/2/3 = 5/36
        ([1.0, 0.5, 1 / 3, 0.5], [1 / 3, 1 / 3, 1 / 3, 2 / 3], 5 / 36),
        # 4) (1+1)/2*.25 + (1+.75)/2*.25 = .25 + .21875 = .46875
        ([1.0, 1.0, 0.75], [0.25, 0.5, 0.75], 0.46875),
        # 5) a single point has no trapezoid
        ([1.0], [0.3], 0.0),
    ],
)
def test_auc_trapezoid_hand_cases(precision: list[float], recall: list[float], expected: float) -> None:
    assert auc_pr_trapezoid(precision, recall) == pytest.approx(expected)


def test_auc_rejects_mismatched_lengths() -> None:
    with pytest.raises(EvaluationError):
        auc_pr_trapezoid([1.0, 0.5], [0.1])


# ---------------------------------------------------------------- PR curve

def test_pr_curve_hand_example() -> None:
    # 5 queries, already sorted by confidence; q4 has no true match (n_pos = 4).
    # accepted:   1    2    3    4    5
    # correct:    T    F    T    F    F      -> tp 1 1 2 2 2
    # precision:  1   1/2  2/3  1/2  2/5
    # recall:    1/4  1/4  2/4  2/4  2/4
    # AUC = (1/2 + 2/3)/2 * 1/4 = 7/48 (all other steps have zero recall change)
    curve = pr_curve([0.9, 0.8, 0.7, 0.6, 0.5], [True, False, True, False, False],
                     [True, True, True, True, False])
    np.testing.assert_allclose(curve.precision, [1, 1 / 2, 2 / 3, 1 / 2, 2 / 5])
    np.testing.assert_allclose(curve.recall, [1 / 4, 1 / 4, 2 / 4, 2 / 4, 2 / 4])
    np.testing.assert_allclose(curve.thresholds, [0.9, 0.8, 0.7, 0.6, 0.5])
    assert curve.n_positives == 4 and curve.n_queries == 5
    assert curve.auc == pytest.approx(7 / 48)
    assert json.loads(json.dumps(curve.to_dict()))["auc"] == pytest.approx(7 / 48)


def test_pr_curve_order_independent_and_ties_grouped() -> None:
    # Ties at 0.9 enter together: thresholds [0.9, 0.5]; tp 1 then 2; accepted 2 then 3.
    curve = pr_curve([0.5, 0.9, 0.9], [True, True, False])
    np.testing.assert_allclose(curve.thresholds, [0.9, 0.5])
    np.testing.assert_allclose(curve.precision, [1 / 2, 2 / 3])
    np.testing.assert_allclose(curve.recall, [1 / 3, 2 / 3])


def test_pr_curve_no_match_is_never_accepted() -> None:
    # q1 (-inf) and q2 (NaN) report no match: only q0 is ever accepted; recall denominator 3.
    curve = pr_curve([0.8, -np.inf, np.nan], [True, False, False])
    np.testing.assert_allclose(curve.precision, [1.0])
    np.testing.assert_allclose(curve.recall, [1 / 3])
    assert curve.auc == 0.0


def test_pr_curve_prepend_zero_recall() -> None:
    # Points (r, p): (0, 1), (1/2, 1), (1/2, 1/2), (1, 2/3)
    # AUC = (1+1)/2*1/2 + 0 + (1/2+2/3)/2*1/2 = 1/2 + 7/24 = 19/24
    curve = pr_curve([0.9, 0.8, 0.7], [True, False, True], [True, False, True], prepend_zero_recall=True)
    np.testing.assert_allclose(curve.recall, [0, 1 / 2, 1 / 2, 1])
    assert curve.auc == pytest.approx(19 / 24)
    assert curve.to_dict()["thresholds"][0] is None


def test_pr_curve_rejects_correct_without_match() -> None:
    with pytest.raises(EvaluationError):
        pr_curve([0.9], [True], [False])


def test_precision_at_full_recall_and_recall_at_full_precision() -> None:
    p = [1.0, 1.0, 2 / 3, 3 / 4, 3 / 5]
    r = [1 / 3, 2 / 3, 2 / 3, 1.0, 1.0]
    assert precision_at_full_recall(p, r) == pytest.approx(3 / 4)
    assert recall_at_full_precision(p, r) == pytest.approx(2 / 3)
    assert precision_at_full_recall([1.0], [0.5]) == 0.0
    assert recall_at_full_precision([0.5], [0.5]) == 0.0


# ---------------------------------------------------------------- Recall@N and coverage

def test_recall_at_n_hand_example() -> None:
    ranked = np.array([[2, 0, 1], [0, 1, 2], [3, 4, 0], [1, -1, -1]])
    truth = [{0}, {2}, {3, 4}, set()]  # q3 has no true match: left out (3 positives)
    # q0 hit at rank 1, q1 at rank 2, q2 at rank 0 -> R@1 = 1/3, R@2 = 2/3, R@3 = 1
    assert recall_at_n(ranked, truth, ns=(1, 2, 3)) == pytest.approx({1: 1 / 3, 2: 2 / 3, 3: 1.0})
    with pytest.raises(EvaluationError):
        recall_at_n(ranked, truth, ns=(5,))
    with pytest.raises(EvaluationError):
        recall_at_n(ranked, truth[:2], ns=(1,))


def test_coverage_hand_example() -> None:
    truth = [{0}, {1, 2}, {3, 4}, set()]
    mask = np.array([False, False, True, False, False])
    # q0: {0} not kept; q1: 2 kept; q2: neither kept; q3 has no truth -> 1/3
    assert coverage(truth, mask) == pytest.approx(1 / 3)
    assert coverage(truth, np.ones(5, bool)) == 1.0


# ---------------------------------------------------------------- protocols on a 4 x 5 example

SIM = np.array(
    [
        [0.90, 0.80, 0.10, 0.00, 0.20],  # q0, truth {0}
        [0.30, 0.70, 0.60, 0.10, 0.00],  # q1, truth {1}
        [0.10, 0.20, 0.30, 0.95, 0.50],  # q2, truth {3, 4}
        [0.20, 0.10, 0.00, 0.30, 0.40],  # q3, no true match
    ]
)
TRUTH = [{0}, {1}, {3, 4}, set()]
MAP = np.array([False, True, True, True, False])  # frames 0 and 4 discarded


def test_map_only_protocol_by_hand() -> None:
    # Database = frames {1, 2, 3}. Best map frames: q0 -> 1 (.8, wrong: its only true place
    # was discarded), q1 -> 1 (.7, correct), q2 -> 3 (.95, correct), q3 -> 3 (.3, wrong).
    # Sorted by confidence: q2 T, q0 F, q1 T, q3 F; positives = 3 (q0, q1, q2)
    # precision 1, 1/2, 2/3, 1/2; recall 1/3, 1/3, 2/3, 2/3
    # AUC = 0 + (1/2 + 2/3)/2 * 1/3 + 0 = 7/36
    res = evaluate_map_only(SIM, TRUTH, MAP, ns=(1, 3))
    np.testing.assert_array_equal(res.best_index, [1, 1, 3, 3])
    np.testing.assert_array_equal(res.correct, [False, True, True, False])
    np.testing.assert_allclose(res.curve.precision, [1, 1 / 2, 2 / 3, 1 / 2])
    np.testing.assert_allclose(res.curve.recall, [1 / 3, 1 / 3, 2 / 3, 2 / 3])
    assert res.auc == pytest.approx(7 / 36)
    assert res.recall_at == pytest.approx({1: 2 / 3, 3: 2 / 3})  # q0 can never be found
    assert res.coverage == pytest.approx(2 / 3)
    assert res.n_positives == 3 and res.n_map == 3 and res.n_refs == 5
    assert res.precision_at_full_recall == 0.0
    assert res.recall_at_full_precision == pytest.approx(1 / 3)
    d = json.loads(json.dumps(res.to_dict(per_query=True, curve=True)))
    assert d["protocol"] == "map-only" and d["recall_at"]["1"] == pytest.approx(2 / 3)


def test_paper_protocol_by_hand() -> None:
    # Full database. Best frames: q0 -> 0 (discarded: "no match", has a true match -> FN),
    # q1 -> 1 (.7, correct), q2 -> 3 (.95, correct), q3 -> 4 (discarded, no true match -> TN).
    # Accepted in order: q2 T, q1 T -> precision 1, 1; recall 1/3, 2/3 (3 positives)
    # AUC = (1 + 1)/2 * (2/3 - 1/3) = 1/3
    res = evaluate_paper(SIM, TRUTH, MAP, ns=(1, 3))
    np.testing.assert_array_equal(res.best_index, [0, 1, 3, 4])
    assert list(np.isinf(res.confidence)) == [True, False, False, True]
    np.testing.assert_allclose(res.curve.precision, [1, 1])
    np.testing.assert_allclose(res.curve.recall, [1 / 3, 2 / 3])
    assert res.auc == pytest.approx(1 / 3)
    # Recall@N counts hits on map frames only: q0's true frame 0 is discarded.
    assert res.recall_at == pytest.approx({1: 2 / 3, 3: 2 / 3})
    assert res.recall_at_full_precision == pytest.approx(2 / 3)
    assert res.options == {"discarded": "false_negative"}


def test_paper_protocol_lenient_reading() -> None:
    # discarded="true_negative": q0 leaves the positives (2 left: q1, q2).
    # precision 1, 1; recall 1/2, 1 -> AUC = (1+1)/2 * 1/2 = 1/2; precision at full recall 1
    res = evaluate_paper(SIM, TRUTH, MAP, ns=(1,), discarded="true_negative")
    np.testing.assert_allclose(res.curve.recall, [1 / 2, 1])
    assert res.auc == pytest.approx(1 / 2)
    assert res.precision_at_full_recall == 1.0
    assert res.recall_at == pytest.approx({1: 1.0})
    with pytest.raises(EvaluationError):
        evaluate_paper(SIM, TRUTH, MAP, discarded="maybe")  # type: ignore[arg-type]


def test_protocols_agree_when_nothing_is_discarded() -> None:
    rng = np.random.default_rng(3)
    q, r = rng.normal(size=(30, 8)), rng.normal(size=(40, 8))
    sim = q @ r.T
    truth = [{int(i)} if i % 4 else set() for i in rng.integers(0, 40, size=30)]
    full = np.ones(40, bool)
    a = evaluate_map_only(sim, truth, full).to_dict()
    b = evaluate_paper(sim, truth, full).to_dict()
    for key in ("auc", "recall_at", "n_positives", "coverage"):
        assert a[key] == b[key]


def test_protocols_accept_match_output() -> None:
    rng = np.random.default_rng(4)
    q = rng.normal(size=(12, 6)).astype(np.float32)
    r = rng.normal(size=(20, 6)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    truth = [{int(i), int(i) + 1} for i in rng.integers(0, 19, size=12)]
    mask = rng.random(20) < 0.5
    via_matrix = evaluate_map_only(q @ r.T, truth, mask, ns=(1, 5))
    via_match = evaluate_map_only(match(q, r, k=5, ref_mask=mask), truth, mask, ns=(1, 5))
    assert via_matrix.auc == pytest.approx(via_match.auc)
    assert via_matrix.recall_at == pytest.approx(via_match.recall_at)
    paper_matrix = evaluate_paper(q @ r.T, truth, mask, ns=(1, 5))
    paper_match = evaluate_paper(match(q, r, k=5), truth, mask, ns=(1, 5))
    assert paper_matrix.auc == pytest.approx(paper_match.auc)
    # Candidates from an unmasked search are refused by the map-only protocol.
    with pytest.raises(EvaluationError, match="outside the map"):
        evaluate_map_only(match(q, r, k=5), truth, mask, ns=(1, 5))


# ---------------------------------------------------------------- truth parsing

def test_parse_truth_nordland_file() -> None:
    path = shared("nordland_dev_truth.json")
    truth = parse_truth(path, n_query=800, n_ref=800)
    assert len(truth) == 800
    assert truth[0] == {0, 1} and truth[5] == {4, 5, 6} and truth[799] == {798, 799}


def test_parse_truth_dict_and_errors(tmp_path: Path) -> None:
    assert parse_truth({"matches": [[0], [], [1, 2]]}, 3, 3) == [{0}, set(), {1, 2}]
    bad_json = tmp_path / "bad.json"
    bad_json.write_text('{"matches": [[0], ')
    with pytest.raises(EvaluationError, match="bad.json"):
        parse_truth(bad_json, 2, 2)
    with pytest.raises(EvaluationError, match="missing.json"):
        parse_truth(tmp_path / "missing.json", 2, 2)
    cases = [
        ({"match": [[0]]}, "matches"),
        ({"matches": [[0], [1]]}, "expected one per query"),  # wrong length for n_query=3
        ({"matches": [[0], [3], [1]]}, "outside"),  # index 3 with n_ref=3
        ({"matches": [[0], [-1], [1]]}, "outside"),
        ({"matches": [[0], [1.5], [1]]}, "integers"),
        ({"matches": [[0], [True], [1]]}, "integers"),
        ({"matches": [[0], 1, [1]]}, "integers"),
    ]
    for k, (data, message) in enumerate(cases):
        f = tmp_path / f"case{k}.json"
        f.write_text(json.dumps(data))
        with pytest.raises(EvaluationError, match=message) as info:
            parse_truth(f, 3, 3)
        assert f"case{k}.json" in str(info.value)


def test_truth_from_positions_local_and_geographic() -> None:
    q = np.array([[0.0, 0.0], [100.0, 0.0], [np.nan, 0.0]])
    r = np.array([[10.0, 0.0], [30.0, 0.0], [100.0, 24.0], [100.0, 26.0]])
    assert truth_from_positions(q, r, tol_m=25.0) == [{0}, {2}, set()]
    # 3-d: z counts
    assert truth_from_positions([[0, 0, 0]], [[0, 0, 20], [0, 0, 30]], tol_m=25.0) == [{0}]
    # At latitude 60 deg one degree of longitude is ~55.8 km: 0.0004 deg ~ 22.3 m, 0.0005 ~ 27.9 m.
    lat = 60.0
    qg = np.array([[lat, 10.0]])
    rg = np.array([[lat, 10.0004], [lat, 10.0005], [lat + 0.0002, 10.0], [lat + 0.0003, 10.0]])
    # 0.0002 deg of latitude ~ 22.2 m, 0.0003 ~ 33.4 m
    assert truth_from_positions(qg, rg, tol_m=25.0, geographic=True) == [{0, 2}]
    # across the antimeridian: 0.0002 deg of longitude at the equator ~ 22.3 m
    assert truth_from_positions([[0.0, 179.9999]], [[0.0, -179.9999]], geographic=True) == [{0}]
    d = 0.0002 * math.pi / 180 * 6_371_008.8
    assert d < 25.0
    with pytest.raises(EvaluationError):
        truth_from_positions(np.zeros((2, 2)), np.zeros((2, 3)))


def test_paper_protocol_three_readings() -> None:
    # map = refs {1, 2}. q0: true {1}, best match ref 0 (discarded), q1: true {2}, best 2 (correct),
    # q2: true {0} only (discarded: uncovered), best 2 (wrong).
    sim = np.array([[0.9, 0.5, 0.1], [0.1, 0.2, 0.8], [0.3, 0.1, 0.7]])
    truth = [{1}, {2}, {0}]
    mask = np.array([False, True, True])
    fn = evaluate_paper(sim, truth, mask, ns=(1,))
    tn = evaluate_paper(sim, truth, mask, ns=(1,), discarded="true_negative")
    un = evaluate_paper(sim, truth, mask, ns=(1,), discarded="uncovered_negative")
    assert list(fn.has_match) == [True, True, True]
    assert list(tn.has_match) == [False, True, True]  # q0's best match was discarded
    assert list(un.has_match) == [True, True, False]  # q2 has no true place in the map
    for res, n_pos in ((fn, 3), (tn, 2), (un, 2)):
        np.testing.assert_allclose(res.curve.precision, [1, 1 / 2])  # q1 right (.8), q2 wrong (.7)
        np.testing.assert_allclose(res.curve.recall, [1 / n_pos, 1 / n_pos])
        assert res.options == {"discarded": res.options["discarded"]}
