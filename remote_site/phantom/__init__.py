"""Breast-tissue training phantom: silicone layer, tumors, fast contact model, named scenes."""

from remote_site.phantom.phantom import Contact, Phantom, PixelGrid, SensorPad, SiliconeLayer
from remote_site.phantom.scenes import make_scene, scene_names
from remote_site.phantom.tumor import Tumor

__all__ = ["Contact", "Phantom", "PixelGrid", "SensorPad", "SiliconeLayer", "Tumor",
           "make_scene", "scene_names"]
