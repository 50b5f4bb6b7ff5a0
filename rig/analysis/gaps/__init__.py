"""The model-gap workflow (issue 6): find where simulation and measurement disagree, name the missing
effect from the docs/MODEL.md vocabulary, add it, show the gap shrink.

    from rig.analysis.gaps import find_gaps
    result = find_gaps([run], model, report_dir="gaps-report")
    result.steps, result.final_gap  # rig.core.actions.gaps_document(result) is the `--json` document
"""

from rig.analysis.gaps.shooting import METRIC
from rig.analysis.gaps.workflow import GapOptions, GapsResult, GapStep, Trial, find_gaps

__all__ = ["METRIC", "GapOptions", "GapStep", "GapsResult", "Trial", "find_gaps"]
