"""Keys of nerfstudio's DataparserOutputs.metadata that the dataparsers write and the core reads: kept below both."""

FISHEYE_CROP_RADIUS = "fisheye_crop_radius"
"""DataparserOutputs.metadata key of CaptureFrames.fisheye_crop_radius, named after transforms.json's file-wide key."""

HELD_OUT = "held_out"
"""DataparserOutputs.metadata key of CaptureFrames.held_out (transforms.json's test_filenames): the continual split's
test frames instead of every --pipeline.datamanager.test-interval-th."""

DEPTH_FILENAMES = "depth_filenames"
"""DataparserOutputs.metadata key of CaptureFrames.depth_filenames (nerfstudio's own key): per frame its depth map, or
None for a frame without one; absent when the capture has no depth."""

DEPTH_UNIT_SCALE_FACTOR = "depth_unit_scale_factor"
"""DataparserOutputs.metadata key (nerfstudio's own) of the metres one unit of the depth files is."""

DEPTH_INTRINSICS = "depth_intrinsics"
"""DataparserOutputs.metadata key of CaptureFrames.depth_intrinsics: (N, 6) fx, fy, cx, cy, width, height of each
frame's depth camera; absent when depth maps share the colour camera's intrinsics (scaled to their size)."""
