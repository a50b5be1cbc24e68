"""Model-discrepancy workflow: where a bench model and the measurement disagree, which effect of
docs/models.md §5 is missing, and how much the gap shrinks when it is added.

`stage_report(columns, ...)` and `scale_report(columns, ...)` run it on in-memory columns and
return the JSON report (docs/datasets.md, `discrepancy`); `service.commands.discrepancy.run` is the
`tiltlab discrepancy` command; `service.discrepancy.report.render_html` the report page.
"""

from service.discrepancy.scale import analyse_scale, scale_report  # noqa: F401
from service.discrepancy.stage import analyse_stage, stage_report  # noqa: F401
