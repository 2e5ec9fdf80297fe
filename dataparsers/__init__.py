"""Dataparsers that read captures in capture order (installed as `continual_nerf.dataparsers`)."""

from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig

continual_demo = DataParserSpecification(
    config=ContinualDemoDataParserConfig(),
    description="A generated room walked through by a camera: the default, needs no download.",
)
