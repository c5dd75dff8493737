"""The two-view prior is RGB only: on an RGB-D folder (7-Scenes) no depth file is read."""

from __future__ import annotations

from mslam.config import load_config
from mslam.system import open_source

SEVEN = "seq/7scenes_redkitchen_f000000-000149"


def test_twoview_source_drops_the_depth_of_an_rgbd_folder(shared_data) -> None:
    src = open_source(str(shared_data / SEVEN), load_config("twoview"), prior="twoview")
    assert not src.sequence.has_depth
    assert src.sequence[0].depth is None and src.sequence[0].rgb.shape[:2] == (120, 160)
    rgbd = open_source(str(shared_data / SEVEN), load_config("rgbd"))
    assert rgbd.sequence.has_depth and rgbd.sequence[0].depth is not None
