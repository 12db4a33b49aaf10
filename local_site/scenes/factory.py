"""``open_scene(spec)``: one string names any scene source.

Spec forms:

* ``"remote"`` (or ``"stream"``): an empty :class:`TactileFrameScene` to feed with frames;
* a path to a ``.npz`` layer file (anything ending in ``.npz`` or naming an existing file);
* a shape name with optional ``key=value`` parameters after a colon, e.g.
  ``"hemisphere"``, ``"hemisphere:radius_mm=4,shore00=30,friction=0.2"``,
  ``"cone:x_mm=10,y_mm=-5,k=0.75"``. Keys are the shape's geometry
  (:func:`~local_site.scenes.virtual_shapes.shape_parameters`) and ``shore00`` or
  ``k``, ``friction``, ``floor_k``, ``floor_friction``.
"""

from __future__ import annotations

import os
from typing import Any

from local_site.render.interpolation import DEFAULT_ORDER
from local_site.scenes.base import OutsidePolicy, SceneSource
from local_site.scenes.layer_file import LayerFileScene
from local_site.scenes.remote_stream import TactileFrameScene
from local_site.scenes.virtual_shapes import SHAPE_NAMES, make_shape_scene
from shared.errors import ConfigError
from shared.hardness import HardnessTable

__all__ = ["REMOTE_SPECS", "open_scene", "parse_shape_spec"]

REMOTE_SPECS = frozenset({"remote", "stream"})


def parse_shape_spec(spec: str) -> tuple[str, dict[str, float]]:
    """Split ``"name:key=value,..."`` into the name and float parameters.

    Raises:
        ConfigError: a malformed parameter list or a non-numeric value.
    """
    name, _, rest = spec.partition(":")
    params: dict[str, float] = {}
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ConfigError(f"scene spec {spec!r}: parameter {item!r} is not key=value")
        if key in params:
            raise ConfigError(f"scene spec {spec!r}: parameter {key!r} given twice")
        try:
            params[key] = float(value)
        except ValueError as err:
            raise ConfigError(f"scene spec {spec!r}: {key}={value!r} is not a number") from err
    return name.strip(), params


def open_scene(spec: str, *, interpolation_order: int = DEFAULT_ORDER,
               outside: OutsidePolicy | None = None,
               hardness: HardnessTable | None = None, **remote_options: Any) -> SceneSource:
    """Open the scene a spec string names.

    Args:
        spec: ``"remote"``, a ``.npz`` path, or ``"shape[:key=value,...]"``.
        interpolation_order: 0, 1 or 3 for grid scenes (layer files, remote stream).
        outside: policy outside a grid scene's extent (default flat at height 0).
        hardness: Shore 00 <-> k table for layer files and shapes given in Shore 00.
        **remote_options: extra keyword arguments of :class:`TactileFrameScene`
            (``default_stiffness_k``, ``stiffness_to_k``); only with ``"remote"``.

    Returns:
        The scene source.

    Raises:
        ConfigError: an unknown spec, a missing file or invalid parameters.
        InputDataError: a layer file with invalid content.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError("a scene spec must be a non-empty string")
    text = spec.strip()
    if text.lower() in REMOTE_SPECS:
        return TactileFrameScene(order=interpolation_order, outside=outside, **remote_options)
    if remote_options:
        raise ConfigError(f"options {sorted(remote_options)} apply to the remote stream only")
    if text.lower().endswith(".npz") or os.path.isfile(text):
        return LayerFileScene.from_file(text, order=interpolation_order, outside=outside,
                                        hardness=hardness)
    name, params = parse_shape_spec(text)
    try:
        return make_shape_scene(name, hardness=hardness, **params)
    except ConfigError as err:
        raise ConfigError(f"scene spec {spec!r}: {err} (a spec is 'remote', a .npz layer "
                          f"file, or one of {', '.join(SHAPE_NAMES)} with optional "
                          f"':key=value,...')") from err
