"""Scene sources for the local station: what the operator's fingertip explores.

All sources implement :class:`SceneSource` (``sample(points_xy_mm) -> SceneSample`` and
a ``version`` counter): virtual shapes, layer files and the remote tactile stream.
:func:`open_scene` builds any of them from a spec string.
"""

from local_site.scenes.base import MAX_SCENE_HEIGHT_MM, OutsidePolicy, SceneSample, SceneSource
from local_site.scenes.factory import open_scene, parse_shape_spec
from local_site.scenes.grid_scene import GridScene
from local_site.scenes.layer_file import (
    LayerFileData,
    LayerFileScene,
    load_layer_file,
    save_layer_file,
)
from local_site.scenes.remote_stream import TactileFrameScene
from local_site.scenes.virtual_shapes import (
    SHAPE_NAMES,
    VirtualShapeScene,
    make_shape_scene,
    shape_gallery,
)

__all__ = [
    "MAX_SCENE_HEIGHT_MM",
    "SHAPE_NAMES",
    "GridScene",
    "LayerFileData",
    "LayerFileScene",
    "OutsidePolicy",
    "SceneSample",
    "SceneSource",
    "TactileFrameScene",
    "VirtualShapeScene",
    "load_layer_file",
    "make_shape_scene",
    "open_scene",
    "parse_shape_spec",
    "save_layer_file",
    "shape_gallery",
]
