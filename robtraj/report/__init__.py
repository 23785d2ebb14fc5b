"""Figures (PNG, matplotlib Agg) and the HTML report; the only place that imports matplotlib."""

from ._discrepancy_figures import (
    gap_figure as gap_figure,
    map_figure as map_figure,
    noise_figure as noise_figure,
    structure_figure as structure_figure,
)
from ._figures import (
    deviation_figure as deviation_figure,
    path_3d_figure as path_3d_figure,
    pose_quality_figure as pose_quality_figure,
    robust_limit as robust_limit,
    velocity_figure as velocity_figure,
    visibility_figure as visibility_figure,
    weighting_figure as weighting_figure,
    workspace_error_figure as workspace_error_figure,
)
from ._html import (
    Figure as Figure,
    Section as Section,
    Summary as Summary,
    Table as Table,
    Value as Value,
    interval_of as interval_of,
    iso_tables as iso_tables,
    write_report as write_report,
)
from ._recording_report import (
    RecordingParts as RecordingParts,
    recording_parts as recording_parts,
    recording_report as recording_report,
)
