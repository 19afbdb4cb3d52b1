"""Camera trajectories in the morphgs convention (OpenCV axes, SPEC §3).

Readers bring recorded cameras in (`from_transforms_json`, `from_colmap`, `from_camera_path`);
`trajectory.checks` is the one validation of cameras read from a file (every reader uses it);
generators make paths (`smooth_path` through keyframes, `orbit`/`ellipse`, `spiral`, and
`for_scene` for scenes with no cameras, `around_cameras` for an orbit where recorded cameras look); `clips` splits a path into fixed-length clips.
"""

from __future__ import annotations

from morphgs.trajectory._common import CaptureError, CropWarning, resize_camera, warn_stretch
from morphgs.trajectory.checks import camera_from_c2w, check_intrinsics, check_quaternion, check_rotation
from morphgs.trajectory.colmap import ColmapView, find_colmap_model, from_colmap, read_colmap_views
from morphgs.trajectory.generators import (
    FILE_UP,
    around_cameras,
    camera_focus,
    ellipse,
    for_scene,
    orbit,
    parse_up,
    robust_bounds,
    scene_up,
    spiral,
)
from morphgs.trajectory.nerfstudio import (
    TransformsFrame,
    from_camera_path,
    from_transforms_json,
    read_transforms_frames,
)
from morphgs.trajectory.smooth import camera_sequence, clips, smooth_path

__all__ = [
    "FILE_UP",
    "CaptureError",
    "CropWarning",
    "ColmapView",
    "TransformsFrame",
    "around_cameras",
    "camera_focus",
    "camera_from_c2w",
    "check_intrinsics",
    "check_quaternion",
    "check_rotation",
    "camera_sequence",
    "clips",
    "ellipse",
    "find_colmap_model",
    "for_scene",
    "from_camera_path",
    "from_colmap",
    "from_transforms_json",
    "orbit",
    "parse_up",
    "read_colmap_views",
    "read_transforms_frames",
    "resize_camera",
    "robust_bounds",
    "scene_up",
    "smooth_path",
    "spiral",
    "warn_stretch",
]
