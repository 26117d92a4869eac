"""The paper's Tables 1-2 and trajectory figures: DAgger with and without the filter."""

from saferace.experiments.paper.presets import PRESETS, Preset, TableSetting
from saferace.experiments.paper.runs import run_paper_tables

__all__ = ["PRESETS", "Preset", "TableSetting", "run_paper_tables"]
