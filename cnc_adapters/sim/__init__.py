"""The virtual machine tool, one adapter backend among the others (python-can's ``virtual`` bus):
a spindle plant, a virtual CNC over OPC UA, an NC interpreter and the in-process ``sim`` adapter.
Speed programs live in :mod:`compensator.programs`, below every layer that uses them."""

from .plant import PRESETS, PlantParams, PlantRun, SpindlePlant, preset

__all__ = ["PRESETS", "PlantParams", "PlantRun", "SpindlePlant", "preset"]
