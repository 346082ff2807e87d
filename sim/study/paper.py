"""The paper's published results, for side-by-side comparison.

Source: Diab, Mohammadkarimi, Rajan, "Artificial Potential Field-Based Path Planning for Cluttered
Environments", IEEE Aerospace Conference 2023, DOI 10.1109/AERO55745.2023.10115857, Table II ("Performance
comparison between the four APF methods for different obstacle densities"), sub-tables (a) N ~ U[20, 45],
(b) N ~ U[45, 70], (c) N ~ U[70, 95]; N_m = 4000 trials each. A-BAPF has no row in Table II; the text only says
it "can achieve a navigation success rate of more than 95 %" (Section "Simulation Results").
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True, kw_only=True)
class PaperRow:
    R_s: float
    M_s: float
    S_m: float
    T_a_ms: float


PAPER_TABLE_II: dict[tuple[str, tuple[int, int]], PaperRow] = {
    ("capf", (20, 45)): PaperRow(R_s=0.333, M_s=91.26, S_m=2.71, T_a_ms=26.80),
    ("bapf", (20, 45)): PaperRow(R_s=0.739, M_s=68.25, S_m=2.37, T_a_ms=26.30),
    ("cr-bapf", (20, 45)): PaperRow(R_s=0.770, M_s=68.39, S_m=2.38, T_a_ms=27.05),
    ("cr-bapf*", (20, 45)): PaperRow(R_s=0.935, M_s=70.47, S_m=2.35, T_a_ms=31.63),
    ("capf", (45, 70)): PaperRow(R_s=0.170, M_s=108.49, S_m=3.22, T_a_ms=52.72),
    ("bapf", (45, 70)): PaperRow(R_s=0.552, M_s=77.82, S_m=2.40, T_a_ms=66.87),
    ("cr-bapf", (45, 70)): PaperRow(R_s=0.490, M_s=69.24, S_m=2.42, T_a_ms=44.18),
    ("cr-bapf*", (45, 70)): PaperRow(R_s=0.873, M_s=76.54, S_m=2.38, T_a_ms=65.95),
    ("capf", (70, 95)): PaperRow(R_s=0.157, M_s=111.93, S_m=3.53, T_a_ms=71.64),
    ("bapf", (70, 95)): PaperRow(R_s=0.407, M_s=70.62, S_m=2.43, T_a_ms=59.84),
    ("cr-bapf", (70, 95)): PaperRow(R_s=0.270, M_s=70.22, S_m=2.52, T_a_ms=60.43),
    ("cr-bapf*", (70, 95)): PaperRow(R_s=0.812, M_s=83.36, S_m=2.44, T_a_ms=108.65),
}
"""Table II of the paper, keyed by (planner name, (N_l, N_u))."""

PAPER_ABAPF_R_S_LOWER_BOUND = 0.95
"""The paper's only A-BAPF number: "a navigation success rate of more than 95 %" (no density given)."""


def paper_row(planner_name: str, n_low: int, n_high: int) -> PaperRow | None:
    return PAPER_TABLE_II.get((planner_name, (n_low, n_high)))
