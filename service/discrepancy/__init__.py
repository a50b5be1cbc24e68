"""Model-discrepancy workflow: where a bench model and the measurement disagree, which effect of
spec/models.md §5 is missing, and how much the gap shrinks when it is added.

`stage_report(columns, ...)` and `scale_report(columns, ...)` run it on in-memory columns and
return the JSON report (spec/datasets.md, `discrepancy`); `service.discrepancy.cli.run` is the
`tiltlab discrepancy` command; `service.discrepancy.report.render_html` the report page.
"""

from service.discrepancy.scale import analyse_scale, scale_report  # noqa: F401
from service.discrepancy.stage import analyse_stage, stage_report  # noqa: F401
