"""Keys of nerfstudio's DataparserOutputs.metadata that the dataparsers write and the core reads: kept below both."""

FISHEYE_CROP_RADIUS = "fisheye_crop_radius"
"""DataparserOutputs.metadata key of CaptureFrames.fisheye_crop_radius, named after transforms.json's file-wide key."""

HELD_OUT = "held_out"
"""DataparserOutputs.metadata key of CaptureFrames.held_out (transforms.json's test_filenames): the continual split's
test frames instead of every --pipeline.datamanager.test-interval-th."""
