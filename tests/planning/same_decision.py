"""Checks shared by the tests that compare bapf-nav's single-agent paths with its batch path, bit for bit."""

from __future__ import annotations

from apf_companion.planning import Decision

#: The per-agent arrays of ``NavState`` (its ``field`` is compared on its own).
NAV_STATE_FIELDS = (
    "target_m",
    "mode",
    "hit_dist_m",
    "best_dist_m",
    "since_best",
    "since_field",
    "prev_dir",
    "trail_m",
    "trail_next",
    "gave_up",
)


def assert_same_decision(single: Decision, row: Decision) -> None:
    """``single`` (from ``step``) equals ``row`` (a row of ``step_batch``): every field, floats to the bit."""
    assert single.reason is row.reason and single.chosen_index == row.chosen_index
    assert (single.n_passing, single.n_safe, single.mu_o_k) == (row.n_passing, row.n_safe, row.mu_o_k)
    if single.next_point_m is None:
        assert row.next_point_m is None
    else:
        assert row.next_point_m is not None
        assert single.next_point_m.tobytes() == row.next_point_m.tobytes()
    assert single.candidate_cost is not None and row.candidate_cost is not None
    assert single.candidate_cost.tobytes() == row.candidate_cost.tobytes()
