"""The restructuring of issue 41 changed no output: ``memlog score``, ``map``, ``localize`` and
``evaluate`` on the shared logs, run through the CLI, write what the code before it wrote
(recorded in ``tests/data/recorded_outputs.json.gz`` by ``python -m tests.recorded_outputs``), timing
fields aside. Strings, integers and structure must be equal; floats within a relative 1e-4."""

from __future__ import annotations

from pathlib import Path

from tests.recorded_outputs import COMMANDS, differences, recorded, summarise


def test_outputs_equal_the_recorded_ones(recorded_run: Path) -> None:
    """(The commands run once for the session: the ``recorded_run`` fixture.)"""
    before = recorded()
    now = summarise(recorded_run)
    assert set(now) == set(before)
    diffs = differences(before, now)
    assert not diffs, f"{len(diffs)} difference(s) from the recorded outputs of {', '.join(COMMANDS)}:\n" + "\n".join(
        diffs[:40])


def test_the_comparison_sees_a_change() -> None:
    """differences() is not blind: a changed kept frame, string or float beyond 1e-4 is reported."""
    before = {"a": [1, 2.0, "x"], "b": {"c": 0.5}}
    assert differences(before, {"a": [1, 2.0, "x"], "b": {"c": 0.5 * (1 + 1e-6)}}) == []
    assert differences(before, {"a": [1, 2.0, "y"], "b": {"c": 0.5}}) == ["/a[2]: recorded 'x', now 'y'"]
    assert differences(before, {"a": [2, 2.0, "x"], "b": {"c": 0.5}}) == ["/a[0]: recorded 1, now 2"]
    assert len(differences(before, {"a": [1, 2.0, "x"], "b": {"c": 0.501}})) == 1
    assert len(differences(before, {"a": [1, 2.0], "b": {"c": 0.5}})) == 1
    assert len(differences(before, {"a": [1, 2.0, "x"], "b": {}})) == 1
    # a float fit's hash (another CPU's SVD bits) is compared as a hash; any other hash exactly
    h1, h2 = "a" * 64, "b" * 64
    assert differences({"m": {"whitening": {"sha256": h1}, "input_sha256": h1}},
                       {"m": {"whitening": {"sha256": h2}, "input_sha256": h1}}) == []
    assert len(differences({"input_sha256": h1}, {"input_sha256": h2})) == 1
    assert len(differences({"patch_pca": h1}, {"patch_pca": "none"})) == 1
