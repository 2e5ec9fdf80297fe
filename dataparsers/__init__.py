"""Dataparsers that read captures in capture order (installed as `continual_nerf.dataparsers`)."""

from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig

continual_demo = DataParserSpecification(
    config=ContinualDemoDataParserConfig(),
    description="A generated room walked through by a camera: the default, needs no download.",
)

continual_nerfstudio = DataParserSpecification(
    config=OrderedCaptureDataParserConfig(),
    description="A nerfstudio transforms.json or COLMAP capture (Tanks and Temples, ...) in capture order: "
    "timestamps, numbers in file names, or file order.",
)
