"""Analysis of measured trajectories: path deviation, ISO 9283 characteristics, TUM export."""

from ._accuracy_after import (
    AccuracyAfterCompensation as AccuracyAfterCompensation,
    accuracy_after_compensation as accuracy_after_compensation,
)
from ._ape import absolute_pose_error as absolute_pose_error
from ._iso_path import (
    CornerCharacteristics as CornerCharacteristics,
    PathCharacteristics as PathCharacteristics,
)
from ._named_model import (
    named_calibration as named_calibration,
    outside_maps as outside_maps,
    pose_calibration as pose_calibration,
)
from ._quat import error_components as error_components, rotation_angle as rotation_angle
from ._search_frames import (
    SEARCH_FRAMES as SEARCH_FRAMES,
    refit_on_all_frames as refit_on_all_frames,
    search_recording as search_recording,
)
from .deviation import (
    DeviationResult as DeviationResult,
    DeviationSummary as DeviationSummary,
    ReferencePath as ReferencePath,
    commanded_path as commanded_path,
    path_deviation as path_deviation,
    point_segment as point_segment,
)
from .iso9283 import (
    DistanceCharacteristics as DistanceCharacteristics,
    Iso9283Result as Iso9283Result,
    PoseCharacteristics as PoseCharacteristics,
    iso9283 as iso9283,
)
from .prediction import (
    Prediction as Prediction,
    predict as predict,
    predicted_tool_poses as predicted_tool_poses,
)
from .tum import write_tum as write_tum
