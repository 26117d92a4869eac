"""Experiments above the learning and evaluation layers: the paper's tables, the safety
table, the robustness sweep and the benchmark protocol with its leaderboard page."""
