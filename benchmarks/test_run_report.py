"""The benchmark's arithmetic: how many runs a case gets (``child.py``), how rounds are pooled
(``measure.py``) and what the report concludes from them (``summary.py``)."""

from __future__ import annotations

import statistics

import child
import measure
import pytest
import summary


@pytest.mark.parametrize(
    ("seconds", "repeats", "budget", "min_seconds", "expected"),
    [
        (0.5, 5, 300.0, 0.0, 5),  # the repeats
        (0.025, 5, 300.0, 1.0, 40),  # more, to fill a second
        (0.001, 5, 300.0, 1.0, child.MAX_TIMED_RUNS),  # but no more than the cap
        (100.0, 5, 300.0, 1.0, 3),  # fewer, to keep to the budget
        (500.0, 5, 300.0, 1.0, 1),  # at least one
    ],
)
def test_planned_repeats(seconds, repeats, budget, min_seconds, expected) -> None:
    assert child.planned_repeats(seconds, repeats, budget, min_seconds) == expected


def _result(mesh: str, vertices: int, round_index: int, times: list[float], peak: int) -> dict:
    case = {
        "section": "scaling",
        "mesh": mesh,
        "method": "numba",
        "threads": 2,
        "dtype": "float32",
        "num_scales": 8,
        "round": round_index,
        "rounds": 2,
    }
    return {
        "ok": True,
        "case": case,
        "vertices": vertices,
        "times_s": times,
        "median_s": statistics.median(times),
        "min_s": min(times),
        "peak_rss": peak,
        "base_rss": peak // 2,
        "round_medians_s": {str(round_index): statistics.median(times)},
    }


def test_rounds_pool_their_runs_and_keep_the_highest_peak() -> None:
    results = [
        _result("icosphere:5", 100, 0, [1.0, 3.0], 10),
        _result("icosphere:6", 400, 0, [4.0, 4.0], 20),
    ]
    assert measure.fold_round(results, _result("icosphere:5", 100, 1, [2.0, 2.0, 8.0], 30))
    assert measure.fold_round(results, _result("icosphere:6", 400, 1, [8.0, 8.0], 5))
    small, large = results
    assert small["times_s"] == [1.0, 3.0, 2.0, 2.0, 8.0]
    assert (small["median_s"], small["min_s"]) == (2.0, 1.0)
    assert (small["peak_rss"], small["base_rss"]) == (30, 15)
    assert (large["peak_rss"], large["median_s"]) == (20, 6.0)
    # per vertex: round 0: 2.0 / 100 and 4.0 / 400; round 1: 2.0 / 100 and 8.0 / 400
    assert summary.per_round_spreads(results) == pytest.approx([2.0, 1.0])
    assert summary.per_vertex_spread(results) == (pytest.approx(2.0 / 1.5), 2)


def test_a_first_round_or_a_failure_is_not_folded() -> None:
    results = [_result("icosphere:5", 100, 0, [1.0], 10)]
    assert not measure.fold_round(results, _result("icosphere:6", 400, 1, [1.0], 10))
    failed = _result("icosphere:5", 100, 1, [1.0], 10) | {"ok": False}
    assert not measure.fold_round(results, failed)
    assert results[0]["times_s"] == [1.0]


def test_only_the_target_mesh_gets_a_speedup_verdict() -> None:
    assert summary.speedup_line("gargoyle_50k.off", 14.4).endswith("(target >= 10x: met)")
    assert summary.speedup_line("gargoyle_50k.off", 9.9).endswith("(target >= 10x: NOT met)")
    assert "no target" in summary.speedup_line("spot.obj", 5.0)


def test_the_committed_report_renders_again_from_its_results(tmp_path) -> None:
    """``run.py --report-from`` rebuilds RESULTS.md from results.json alone, word for word."""
    import run

    committed = run.BENCH_DIR / "results.json"
    args = run.parse_args(["--report-from", str(committed), "--output-dir", str(tmp_path)])
    assert run.rerender(args) == 0
    expected = (run.BENCH_DIR / "RESULTS.md").read_text()
    assert (tmp_path / "RESULTS.md").read_text() == expected
    assert (tmp_path / "scaling.png").is_file()
