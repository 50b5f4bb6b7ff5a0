"""The model-gap workflow (issue 6): find where simulation and measurement disagree, name the missing
effect from the docs/MODEL.md vocabulary, add it, show the gap shrink.

    from model.gaps import find_gaps
    result = find_gaps([run], model, report_dir="gaps-report")
    result.to_json()  # docs/INTERFACE.md's `hdrig gaps --json` document
"""

from model.gaps.shooting import METRIC
from model.gaps.workflow import GapOptions, GapsResult, GapStep, Trial, find_gaps

__all__ = ["METRIC", "GapOptions", "GapStep", "GapsResult", "Trial", "find_gaps"]
