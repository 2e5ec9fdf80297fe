"""Dataparsers that read captures in capture order (installed as `continual_nerf.dataparsers`)."""

from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig
from continual_nerf.dataparsers.scannet_dataparser import ContinualScanNetDataParserConfig
from continual_nerf.dataparsers.stream_dataparser import StreamDataParserConfig
from continual_nerf.dataparsers.tum_dataparser import ContinualTumDataParserConfig
from continual_nerf.dataparsers.waymo_dataparser import WaymoDataParserConfig

continual_demo = DataParserSpecification(
    config=ContinualDemoDataParserConfig(),
    description="A generated room walked through by a camera: the default, needs no download.",
)

continual_nerfstudio = DataParserSpecification(
    config=OrderedCaptureDataParserConfig(),
    description="A nerfstudio transforms.json or COLMAP capture (Tanks and Temples, ...) in capture order: "
    "timestamps, numbers in file names, or file order.",
)

continual_scannet = DataParserSpecification(
    config=ContinualScanNetDataParserConfig(),
    description="A ScanNet scene in capture order: SensReader's exported folder or the raw .sens file (read streaming).",
)

continual_tum = DataParserSpecification(
    config=ContinualTumDataParserConfig(),
    description="A TUM RGB-D sequence in capture order, images posed from groundtruth.txt by timestamp.",
)

continual_waymo = DataParserSpecification(
    config=WaymoDataParserConfig(),
    description="A Waymo Open Dataset segment (v2 Parquet root or v1 .tfrecord), chosen cameras split by time.",
)

continual_stream = DataParserSpecification(
    config=StreamDataParserConfig(),
    description="A capture folder another process is still writing, one frame JSON at a time (continual-ngp-stream).",
)
