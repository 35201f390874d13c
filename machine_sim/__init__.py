"""The virtual machine tool: a spindle plant, an NC interpreter, a virtual CNC over OPC UA, the
emulated controls with their servers (PLCs, FOCAS, Haas MDC, a Modbus chiller) and the in-process
``sim`` link, which the link registry names like any other backend (python-can's ``virtual``
bus). It sits above the controller links (it serves and uses their protocols) and below
calibration (the cooling studies run on it); the edge box never imports it. Speed programs live
in :mod:`compensator.speed_programs`, below every layer that uses them."""

from .plant import PRESETS, PlantParams, PlantRun, SpindlePlant, preset

__all__ = ["PRESETS", "PlantParams", "PlantRun", "SpindlePlant", "preset"]
